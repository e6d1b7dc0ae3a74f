"""The viewer's read side: the scan list, one scan's mesh and skin colours, navigation, images.

Every scan says how it ended (``state``, ``in_progress``, ``reason``) and which images it
lacks per phone and why (``missing_by_phone``, ``missing``: the same words as the QA report);
the sharp skin is analysis/skin_map.py's one measure, from the report's ``skin.json`` in the
list and from the coloured mesh itself in the viewer (``/skin``).

A scan is named in URLs by its folder name and found by listing the store, never by joining
a request's text onto a path; image files are the ones the manifest lists as verified.
Reading a scan (its manifest, plan, rig and calibration files) and the heavy work (loading a
mesh, building the ray-casting scene) run off the event loop, which carries the rig's
heartbeats in the daemon; what was read is kept for the few most recently opened scans and read
again only when the manifest or the mesh is another file (a scan in progress rewrites its
manifest after every image).
"""

from __future__ import annotations

import asyncio
import json
from collections import OrderedDict
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import structlog
from aiohttp import web

from analysis.navigate import NavigationError, Navigator
from analysis.scan_views import ScanRecord, open_scan
from analysis.skin_map import mesh_digest, payload_shares, read_skin_mesh, read_skin_shares, skin_mesh, vertex_skin
from daemon.clinic.patient import Patient
from daemon.records.atomic import StoreError
from daemon.records.manifest import ImageStatus, Manifest, ManifestError
from daemon.records.store import ScanStore
from web import glb, images, keys

log = structlog.get_logger("web.scans")

MIPMAP_LEVELS_HEADER = "Tbp-Mipmap-Levels"
"""Where each mipmap level lies on /body/texture/mipmaps' sheet: JSON [[x, y, width, height], ...]."""


def json_error(status: type[web.HTTPException], error: Exception | str) -> web.HTTPException:
    """An HTTP error whose body is {"error": {"type", "message"}}."""
    kind = type(error).__name__ if isinstance(error, Exception) else status.__name__
    text = json.dumps({"error": {"type": kind, "message": str(error)}})
    if status is web.HTTPRequestEntityTooLarge:
        return status(max_size=0, actual_size=0, text=text, content_type="application/json")
    return status(text=text, content_type="application/json")


class OpenScan:
    """What the viewer keeps of one scan: record, navigator, mesh bytes, previews."""

    def __init__(self, record: ScanRecord, stamp: tuple[Any, ...]) -> None:
        self.record = record
        self.stamp = stamp
        self.navigator: Navigator | None = None
        self.mesh: Any = None
        self.mesh_bytes: bytes | None = None
        self.shares: dict[str, float] | None = None
        self.previews: OrderedDict[tuple[Any, ...], Any] = OrderedDict()
        """Scaled images and crops (bytes), the body's preview, atlas and mipmaps (bytes, content
        type, headers)."""
        self.lock = asyncio.Lock()
        self.warming: asyncio.Task[Any] | None = None

    async def navigator_ready(self) -> Navigator:
        """The navigator, built off the loop once (the ray scene takes about a second); 409 when
        the scan's mesh is missing or unreadable."""
        navigator: Navigator = await _from_mesh(self, self.navigator_now)
        return navigator

    async def mesh_ready(self) -> Any:
        """The scan's mesh, read off the loop once; 409 when it is missing or unreadable."""
        return await _from_mesh(self, self.mesh_now)

    def mesh_now(self) -> Any:
        if self.mesh is None:
            self.mesh = self.record.mesh()
        return self.mesh

    def navigator_now(self) -> Navigator:
        if self.navigator is None:
            navigator = Navigator(self.record, self.mesh_now())
            navigator.prepare()
            self.navigator = navigator
        return self.navigator

    def mesh_payload(self) -> bytes:
        """The coloured mesh for the viewer (analysis.skin_map.skin_mesh): the one the QA report
        stored, or computed now for a scan without it."""
        if self.mesh_bytes is None:
            payload = read_skin_mesh(self.record)
            if payload is None:
                mesh = self.mesh_now()
                payload = skin_mesh(mesh, vertex_skin(self.record, mesh)["status"], mesh_digest(self.record))
            self.mesh_bytes = payload
        return self.mesh_bytes

    def skin_shares(self) -> dict[str, float]:
        """The sharp, blurred and unseen shares of the coloured mesh's area (analysis.skin_map)."""
        if self.shares is None:
            self.shares = payload_shares(self.mesh_payload())
        return self.shares


class ScanLibrary:
    """The store as the viewer sees it, with the last few opened scans kept in memory."""

    KEEP = 3
    PREVIEWS = 600

    def __init__(self, store: ScanStore, rig_path: Path | None = None) -> None:
        self.store = store
        self.rig_path = rig_path
        self._open: OrderedDict[str, OpenScan] = OrderedDict()
        self._reading: dict[str, asyncio.Lock] = {}

    def folder(self, name: str) -> Path:
        """The scan folder called ``name``; 404 unless it is one of the store's folders."""
        for path in self.store.folders():
            if path.name == name:
                return path
        raise json_error(web.HTTPNotFound, f"no scan {name[:80]!r} in the store")

    def listing(self) -> list[dict[str, Any]]:
        from analysis.marks import MarkError, read_marks

        rows = []
        for path in reversed(self.store.folders()):
            try:
                m = self.store.open(path).manifest
            except ManifestError as exc:
                rows.append({"folder": path.name, "error": str(exc)})
                continue
            try:
                marks = len(read_marks(path).marks)
            except MarkError:
                marks = None
            rows.append({
                "folder": path.name, "scan_id": m.scan_id, "created_utc": m.created_utc,
                "ended_utc": m.ended_utc, **ending(m), "counts": m.counts(), "plan": m.plan_summary,
                "sharp_skin": (read_skin_shares(path) or {}).get("sharp"),
                "has_mesh": "mesh" in m.files,
                "report": (path / "report" / "index.html").is_file(), "marks": marks,
                "patient": None if m.patient is None else m.patient.as_dict(),
                "accession_number": None if m.study is None else m.study.accession_number,
            })
        return rows

    def patient_of(self, name: str) -> Patient | None:
        """The patient of the scan called ``name`` (404 unless it is in the store, 409 when its
        manifest cannot be read)."""
        try:
            return self.store.open(self.folder(name)).manifest.patient
        except StoreError as exc:
            raise json_error(web.HTTPConflict, exc) from exc

    def _stamp(self, path: Path) -> tuple[Any, ...]:
        """The identity of the scan's manifest and mesh: a rewrite (atomic rename) is another file."""
        manifest = (path / "manifest.json").stat()
        try:
            mesh = (path / "mesh.ply").stat()
        except FileNotFoundError:  # the scan has not reached its depth sweep
            return manifest.st_ino, manifest.st_size, manifest.st_mtime_ns, None
        return manifest.st_ino, manifest.st_size, manifest.st_mtime_ns, (mesh.st_ino, mesh.st_mtime_ns)

    def _read(self, name: str, known: tuple[Any, ...] | None) -> tuple[tuple[Any, ...], ScanRecord | None]:
        """In a thread: the scan's current stamp, and its record when the stamp is not ``known``."""
        path = self.folder(name)
        try:
            stamp = self._stamp(path)
            if stamp == known:
                return stamp, None
            return stamp, open_scan(path, self.rig_path)
        except OSError as exc:  # removed or unreadable meanwhile: read as a scan folder, it says why
            raise json_error(web.HTTPConflict, f"{name[:80]}: {exc.strerror or exc}") from exc
        except StoreError as exc:  # no manifest, a listed file missing, another rig file
            raise json_error(web.HTTPConflict, exc) from exc

    async def opened(self, name: str) -> OpenScan:
        """The scan, read again (in a thread) when its manifest or mesh changed since last time;
        requests for one scan at once share one read."""
        lock = self._reading.setdefault(name, asyncio.Lock())
        async with lock:
            scan = self._open.get(name)
            stamp, record = await _off_loop(self._read, name, scan.stamp if scan is not None else None)
            if record is not None:
                scan = self._open[name] = OpenScan(record, stamp)
        assert scan is not None
        self._open.move_to_end(name)
        while len(self._open) > self.KEEP:
            self._open.popitem(last=False)
        return scan


def ending(m: Manifest) -> dict[str, Any]:
    """How a scan ended, for the list and the viewer: its state, whether it still runs (or was
    left by a daemon that stopped), the reason, and its missing images per phone and why."""
    return {"state": m.state.value, "in_progress": m.in_progress, "reason": m.reason,
            "missing_by_phone": m.missing_by_phone(), "missing": m.missing_summary()}


async def _off_loop(fn: Any, *args: Any) -> Any:
    return await asyncio.get_running_loop().run_in_executor(None, fn, *args)


def _library(request: web.Request) -> ScanLibrary:
    return request.app[keys.LIBRARY]


async def list_scans(request: web.Request) -> web.Response:
    return web.json_response({"scans": await _off_loop(_library(request).listing)})


async def scan_detail(request: web.Request) -> web.Response:
    scan = await _library(request).opened(request.match_info["folder"])
    rec = scan.record
    rig = rec.rig
    m = rec.manifest
    ended = not m.in_progress
    images_out = [{"file": i.file, "camera_id": i.camera_id, "camera_index": i.camera_index,
                   "angle_index": i.angle_index, "planned_angle_deg": i.planned_angle_deg,
                   "actual_angle_deg": i.actual_angle_deg, "focus_mm": i.focus_mm, "status": i.status.value,
                   "error": i.error, "missing_reason": _value(i.why_missing() if ended else i.missing_reason)}
                  for i in rec.images]
    return web.json_response({
        "folder": rec.path.name, "scan_id": m.scan_id, **ending(m),
        "created_utc": m.created_utc, "counts": m.counts(), "plan": m.plan_summary,
        "cameras": [p.id for p in rig.phones], "angles_deg": [float(a) for a in rig.capture.angles_deg],
        "image_width_px": rig.optics.image_width_px, "image_height_px": rig.optics.image_height_px,
        "has_mesh": "mesh" in m.files, "has_body": "body" in m.files,
        "report": (rec.path / "report" / "index.html").is_file(),
        "patient": None if m.patient is None else m.patient.as_dict(),
        "study": None if m.study is None else m.study.as_dict(),
        "images": images_out,
    })


async def _from_mesh(scan: OpenScan, make: Callable[[], Any]) -> Any:
    """What ``make`` builds from the scan's mesh, off the loop under the scan's lock; 409 when the
    scan has no mesh (it ended before the depth sweep) or its mesh cannot be read."""
    async with scan.lock:
        try:
            return await _off_loop(make)
        except StoreError as exc:
            raise json_error(web.HTTPConflict, exc) from exc


async def scan_mesh(request: web.Request) -> web.Response:
    scan = await _library(request).opened(request.match_info["folder"])
    payload = await _from_mesh(scan, scan.mesh_payload)
    if scan.warming is None:  # the first click comes soon: build the navigator meanwhile
        scan.warming = asyncio.create_task(scan.navigator_ready(), name=f"navigator-{scan.record.path.name}")
        scan.warming.add_done_callback(lambda task: task.cancelled() or task.exception())  # a click reports it
    return web.Response(body=payload, content_type="application/octet-stream",
                        headers={"Cache-Control": "private, max-age=60"})


def _body_path(scan: OpenScan) -> Path:
    try:
        path = scan.record.folder.listed("body")
    except StoreError as exc:  # listed, but gone from the disk
        raise json_error(web.HTTPNotFound, exc) from exc
    if path is None:
        raise json_error(web.HTTPNotFound, "this scan has no textured body (tbp texture SCAN_DIR makes one)")
    return path


async def _from_body(request: web.Request, scan: OpenScan, level: str,
                     make: Callable[[bytes], tuple[bytes, str] | tuple[bytes, str, dict[str, str]]]) -> web.Response:
    """What ``make`` builds from body.glb's bytes (its bytes, content type and any headers), off
    the loop, kept with the scan's previews while the file is the same; 422 naming what is wrong
    when body.glb is not a textured glTF binary."""
    path = _body_path(scan)
    stat = path.stat()
    key = ("body", level, stat.st_mtime_ns, stat.st_size)
    kept = scan.previews.get(key)
    if kept is None:
        try:
            kept = await _off_loop(lambda: make(path.read_bytes()))
        except glb.GlbError as exc:
            raise json_error(web.HTTPUnprocessableEntity, f"{path.name}: {exc}") from exc
        _keep(_library(request), scan, key, kept)
    data, content_type, *headers = kept
    return web.Response(body=data, content_type=content_type,
                        headers={"Cache-Control": "private, max-age=60", **(headers[0] if headers else {})})


async def scan_body(request: web.Request) -> web.StreamResponse:
    """The scan's textured body (body.glb, glTF binary in metres: analysis/body_texture.py);
    ``?texture=preview``: the same with its atlas scaled down (web/glb.py), what the viewer shows
    while the full atlas comes from ``body/texture``."""
    scan = await _library(request).opened(request.match_info["folder"])
    level = request.query.get("texture", "full")
    if level == "full":
        return web.FileResponse(_body_path(scan), headers={"Content-Type": "model/gltf-binary",
                                                           "Cache-Control": "private, max-age=60"})
    if level != "preview":
        raise json_error(web.HTTPBadRequest, f"texture={level[:20]!r}: full or preview")
    return await _from_body(request, scan, level, lambda data: (glb.preview(data), "model/gltf-binary"))


async def scan_body_texture(request: web.Request) -> web.Response:
    """The textured body's full atlas: body.glb's base colour image as stored (JPEG)."""
    scan = await _library(request).opened(request.match_info["folder"])
    return await _from_body(request, scan, "texture", glb.texture_image)


async def scan_body_mipmaps(request: web.Request) -> web.Response:
    """The full atlas' mipmap levels 1, 2, ... down to 1 x 1 on one JPEG sheet (web/glb.py
    mipmaps); the ``Tbp-Mipmap-Levels`` header lists where each lies on it, [x, y, width,
    height] from level 1 on. The viewer uploads them with the atlas instead of building them."""
    scan = await _library(request).opened(request.match_info["folder"])

    def sheet(data: bytes) -> tuple[bytes, str, dict[str, str]]:
        image, levels = glb.mipmaps(data)
        return image, "image/jpeg", {MIPMAP_LEVELS_HEADER: json.dumps(levels, separators=(",", ":"))}

    return await _from_body(request, scan, "mipmaps", sheet)


async def scan_skin(request: web.Request) -> web.Response:
    """The sharp skin of the coloured mesh the viewer shows: {"sharp", "blurred", "unseen"}
    shares of its area."""
    scan = await _library(request).opened(request.match_info["folder"])
    return web.json_response(await _from_mesh(scan, scan.skin_shares))


def _keep(library: ScanLibrary, scan: OpenScan, key: tuple[Any, ...], value: Any) -> None:
    """Keep what was built for the scan, the oldest dropped beyond the library's bound."""
    scan.previews[key] = value
    while len(scan.previews) > library.PREVIEWS:
        scan.previews.popitem(last=False)


def _value(reason: Any) -> str | None:
    return None if reason is None else reason.value


def _number(request: web.Request, key: str, kind: type = float) -> Any:
    text = request.query.get(key)
    if text is None:
        return None
    try:
        value = kind(text)
    except ValueError:
        raise json_error(web.HTTPBadRequest, f"{key}={text[:40]!r}: expected a number") from None
    if kind is float and not np.isfinite(value):
        raise json_error(web.HTTPBadRequest, f"{key}={text[:40]!r}: expected a finite number")
    return value


async def navigate(request: web.Request) -> web.Response:
    """?x=&y=&z= (mm) or ?vertex=I; &count=N (default every image that sees the spot)."""
    scan = await _library(request).opened(request.match_info["folder"])
    vertex = _number(request, "vertex", int)
    xyz = [_number(request, k) for k in ("x", "y", "z")]
    count = _number(request, "count", int)
    if vertex is None and any(v is None for v in xyz):
        raise json_error(web.HTTPBadRequest, "give x, y and z (mm) or vertex")
    navigator = await scan.navigator_ready()
    try:
        answer = await _off_loop(lambda: navigator.query(
            point=None if vertex is not None else np.array(xyz), vertex=vertex, count=count))
    except NavigationError as exc:
        raise json_error(web.HTTPBadRequest, exc) from exc
    return web.json_response(answer)


def _image_path(scan: OpenScan, name: str) -> Path:
    folder = scan.record.path
    for image in scan.record.images:
        if image.status is ImageStatus.VERIFIED and image.file and Path(image.file).name == name:
            path = (folder / image.file).resolve()
            if path.parent != (folder / "images").resolve() or not path.is_file():
                break
            return path
    raise json_error(web.HTTPNotFound, f"no verified image {name[:80]!r} in this scan")


async def image(request: web.Request) -> web.StreamResponse:
    """images/NAME: the original; ?size=thumb|preview scaled; ?u=&v=&half= a zoomed crop (full-resolution px)."""
    library = _library(request)
    scan = await library.opened(request.match_info["folder"])
    path = _image_path(scan, request.match_info["name"])
    size = request.query.get("size")
    u, v, half = _number(request, "u"), _number(request, "v"), _number(request, "half")
    if size is None and u is None:
        return web.FileResponse(path, headers={"Cache-Control": "private, max-age=3600"})
    if u is not None:
        if v is None:
            raise json_error(web.HTTPBadRequest, "a crop needs u and v (full-resolution pixels)")
        key: tuple[Any, ...] = (path.name, "crop", round(u, 1), round(v, 1), half or 150.0)
        width = scan.record.rig.optics.image_width_px
        make = lambda: images.crop(path, u, v, width, half or 150.0)
    elif size in ("thumb", "preview"):
        key = (path.name, size)
        make = lambda: images.scaled(path, images.THUMB_PX if size == "thumb" else images.PREVIEW_PX)
    else:
        raise json_error(web.HTTPBadRequest, f"size={size[:20]!r}: thumb or preview")
    data = scan.previews.get(key)
    if data is None:
        try:
            data = await _off_loop(make)
        except images.ImageRequestError as exc:
            raise json_error(web.HTTPBadRequest, exc) from exc
        except images.ImageUnreadable as exc:  # damaged in the store: the scan's check names it too
            log.warning("web_image_unreadable", folder=scan.record.path.name, image=path.name, error=str(exc))
            raise json_error(web.HTTPInternalServerError, exc) from exc
        _keep(library, scan, key, data)
    return web.Response(body=data, content_type="image/jpeg", headers={"Cache-Control": "private, max-age=3600"})


async def report_file(request: web.Request) -> web.StreamResponse:
    """The scan's QA report (report/index.html and its figures)."""
    folder = _library(request).folder(request.match_info["folder"])
    name = request.match_info.get("name") or "index.html"
    report = (folder / "report").resolve()
    path = (report / name).resolve()
    if path.parent != report or not path.is_file() or path.suffix not in (".html", ".png"):
        raise json_error(web.HTTPNotFound, f"no report file {name[:80]!r}")
    return web.FileResponse(path)


def routes(app: web.Application) -> None:
    app.router.add_get("/api/scans", list_scans)
    app.router.add_get("/api/scans/{folder}", scan_detail)
    app.router.add_get("/api/scans/{folder}/mesh", scan_mesh)
    app.router.add_get("/api/scans/{folder}/skin", scan_skin)
    app.router.add_get("/api/scans/{folder}/body", scan_body)
    app.router.add_get("/api/scans/{folder}/body/texture", scan_body_texture)
    app.router.add_get("/api/scans/{folder}/body/texture/mipmaps", scan_body_mipmaps)
    app.router.add_get("/api/scans/{folder}/navigate", navigate)
    app.router.add_get("/api/scans/{folder}/images/{name}", image)
    app.router.add_get("/scans/{folder}/report/", report_file)
    app.router.add_get("/scans/{folder}/report/{name}", report_file)
