"""Lesion marks over the web: list (with the marks carried from the earlier scan), add, delete,
and name the earlier scan to compare with. Writes pass the access policy first.

Each listed mark has its number (the label on the body) and its body region
(analysis/body_regions.py, from this scan's mesh; the list groups by it). A new mark is refused
with the reason, never stored: an empty name (400), a point farther than ``ON_BODY_MM`` from this
scan's body surface (400, ``MarkOffBody``, naming the distance), a point within ``SAME_SPOT_MM`` of
an existing mark (409, ``MarkDuplicate``, naming that mark)."""

from __future__ import annotations

import asyncio
import json
from collections import OrderedDict
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from aiohttp import web

from analysis.body_regions import REGIONS, BodyFrame
from analysis.mark_match import PictureMatcher
from analysis.marks import (
    MarkBook,
    MarkDuplicate,
    MarkError,
    check_mark_id,
    new_mark,
    place_mark,
    read_marks,
    write_marks,
)
from analysis.registration import MarkCarrier, RegistrationError
from web import keys
from web.patients import check_same_patient
from web.scans import ScanLibrary, _off_loop, json_error

MAX_BODY = 16 * 1024


def _library(request: web.Request) -> ScanLibrary:
    return request.app[keys.LIBRARY]


async def read_json(request: web.Request) -> dict[str, Any]:
    """The request's JSON object, after the access check; 4xx for anything else."""
    request.app[keys.ACCESS].check_write(request)
    if request.content_length is not None and request.content_length > MAX_BODY:
        raise json_error(web.HTTPRequestEntityTooLarge, f"body of {request.content_length} bytes; at most {MAX_BODY}")
    raw = await request.content.read(MAX_BODY + 1)
    if len(raw) > MAX_BODY:
        raise json_error(web.HTTPRequestEntityTooLarge, f"body longer than {MAX_BODY} bytes")
    try:
        body = json.loads(raw or b"{}")
    except ValueError as exc:
        raise json_error(web.HTTPBadRequest, f"body is not JSON: {exc}") from None
    if not isinstance(body, dict):
        raise json_error(web.HTTPBadRequest, f"body must be a JSON object, not {type(body).__name__}")
    return body


@dataclass
class CarriedPair:
    """One earlier -> later registration, both scans' pictures, and every point carried so far
    (a point's place is kept: the viewer lists the marks again after each change)."""

    carrier: MarkCarrier
    pictures: PictureMatcher
    done: dict[tuple[float, float, float], tuple[Any, ...]] = field(default_factory=dict)

    def carry(self, points: list[tuple[float, float, float]]) -> list[tuple[Any, ...]]:
        """(carried point, local fit rmse, picture score or NaN, later surface's gap, the two
        surfaces apart around it, the doubt tests it failed: ``surface_gap``, ``surfaces_apart``)
        for each point."""
        new = [p for p in dict.fromkeys(points) if p not in self.done]
        if new:
            carried = self.carrier.carry(np.array(new), self.pictures)
            for key, point, rmse, score, gap, apart, departs, part in zip(
                    new, carried.points_mm, carried.fit_rmse_mm, carried.picture_score, carried.surface_gap_mm,
                    carried.surfaces_apart_mm, carried.surface_departs, carried.surfaces_part):
                doubt = [why for why, failed in (("surface_gap", departs), ("surfaces_apart", part)) if failed]
                self.done[key] = (point, rmse, score, gap, apart, doubt)
        return [self.done[p] for p in points]


class Carriers:
    """Registrations between an earlier and a later scan, kept for a few pairs."""

    KEEP = 4

    def __init__(self) -> None:
        self._fits: OrderedDict[tuple[Any, ...], CarriedPair] = OrderedDict()
        self._lock = asyncio.Lock()

    async def get(self, library: ScanLibrary, earlier: str, later: str) -> CarriedPair:
        a, b = await library.opened(earlier), await library.opened(later)
        key = (earlier, a.stamp, later, b.stamp)
        async with self._lock:
            if key not in self._fits:
                source, target = await a.navigator_ready(), await b.navigator_ready()
                carrier = await _off_loop(MarkCarrier, source.mesh, target.mesh)
                self._fits[key] = CarriedPair(carrier, PictureMatcher(source, target))
                while len(self._fits) > self.KEEP:
                    self._fits.popitem(last=False)
            self._fits.move_to_end(key)
            return self._fits[key]


def _book(folder: Any) -> MarkBook:
    try:
        return read_marks(folder)
    except MarkError as exc:
        raise json_error(web.HTTPConflict, exc) from exc


async def _frame(library: ScanLibrary, name: str) -> BodyFrame | None:
    """The body frame of a scan's mesh (None for a scan without one)."""
    scan = await library.opened(name)
    if "mesh" not in scan.record.manifest.files:
        return None
    mesh = await scan.mesh_ready()
    return await _off_loop(lambda: BodyFrame.of_vertices(np.asarray(mesh.vertices)))


def _with_regions(frame: BodyFrame | None, marks: list[dict[str, Any]]) -> list[dict[str, Any]]:
    regions = frame.regions([m["point_mm"] for m in marks]) if frame is not None and marks else [None] * len(marks)
    return [{**m, "region": r} for m, r in zip(marks, regions)]


async def list_marks(request: web.Request) -> web.Response:
    """This scan's marks, and the earlier scan's marks carried onto this body, each with its body
    region; ``body``: the body frame the regions are of (the viewer sets the labels off the skin
    away from its axis)."""
    library = _library(request)
    name = request.match_info["folder"]
    book = _book(library.folder(name))
    frame = await _frame(library, name)
    out: dict[str, Any] = {"previous_scan": book.previous_scan,
                           "marks": _with_regions(frame, [m.as_dict() for m in book.marks]),
                           "carried": [], "registration": None, "body": None if frame is None else frame.as_dict(),
                           "regions": list(REGIONS)}
    if book.previous_scan:
        earlier = _book(library.folder(book.previous_scan))
        try:
            await check_same_patient(library, name, book.previous_scan)
        except web.HTTPBadRequest as exc:  # a marks file naming another patient's scan: nothing carried
            out["registration"] = {"error": json.loads(exc.text or "{}")["error"]["message"]}
            return web.json_response(out)
        if earlier.marks:
            try:
                pair = await request.app[keys.CARRIERS].get(library, book.previous_scan, name)
                places = await _off_loop(pair.carry, [m.point_mm for m in earlier.marks])
            except RegistrationError as exc:
                out["registration"] = {"error": str(exc)}
            else:
                out["registration"] = {"fitness": pair.carrier.whole.fitness, "rmse_mm": pair.carrier.whole.rmse_mm}
                out["carried"] = _with_regions(frame, [
                    {**m.as_dict(), "point_mm": p.tolist(), "from_point_mm": list(m.point_mm), "fit_rmse_mm": float(r),
                     "placed_by": "shape" if np.isnan(score) else "pictures",
                     "picture_score": None if np.isnan(score) else float(score),
                     "surface_gap_mm": float(gap), "surfaces_apart_mm": float(apart), "doubt": doubt,
                     "in_doubt": bool(doubt)}
                    for m, (p, r, score, gap, apart, doubt) in zip(earlier.marks, places)])
    return web.json_response(out)


async def _surface_distance_mm(library: ScanLibrary, name: str, point: tuple[float, float, float]) -> float:
    """How far ``point`` is from the scan's mesh surface (mm); 409 for a scan without a mesh."""
    scan = await library.opened(name)
    if "mesh" not in scan.record.manifest.files:
        raise json_error(web.HTTPConflict, f"scan {name} has no body mesh: marks lie on the body")
    navigator = await scan.navigator_ready()
    closest, _ = await _off_loop(navigator.scene.closest_faces, np.array([point]))
    return float(np.linalg.norm(closest[0] - np.array(point)))


async def add_mark(request: web.Request) -> web.Response:
    body = await read_json(request)
    library = _library(request)
    name = request.match_info["folder"]
    folder = library.folder(name)
    try:
        mark = new_mark(body.get("name"), body.get("point_mm"), body.get("carried_from"))
        if mark.carried_from is not None and not isinstance(mark.carried_from, dict):
            raise MarkError(f"carried_from {mark.carried_from!r}: expected an object")
        distance = await _surface_distance_mm(library, name, mark.point_mm)
        book = _book(folder)
        mark = place_mark(book, mark, distance)
        await _off_loop(write_marks, folder, book)
    except MarkDuplicate as exc:
        raise json_error(web.HTTPConflict, exc) from exc
    except MarkError as exc:
        raise json_error(web.HTTPBadRequest, exc) from exc
    return web.json_response(mark.as_dict(), status=201)


async def delete_mark(request: web.Request) -> web.Response:
    await read_json(request)
    folder = _library(request).folder(request.match_info["folder"])
    try:
        mark_id = check_mark_id(request.match_info["mark"])
    except MarkError as exc:
        raise json_error(web.HTTPBadRequest, exc) from exc
    book = _book(folder)
    kept = [m for m in book.marks if m.id != mark_id]
    if len(kept) == len(book.marks):
        raise json_error(web.HTTPNotFound, f"no mark {mark_id} on this scan")
    book.marks = kept
    await _off_loop(write_marks, folder, book)
    return web.json_response({"deleted": mark_id})


async def set_previous(request: web.Request) -> web.Response:
    """{"previous_scan": FOLDER | null}: an earlier scan of the same patient (another patient's, or
    any for a scan without a patient, is refused)."""
    body = await read_json(request)
    library = _library(request)
    name = request.match_info["folder"]
    folder = library.folder(name)
    previous = body.get("previous_scan")
    if previous is not None:
        if not isinstance(previous, str):
            raise json_error(web.HTTPBadRequest, f"previous_scan {previous!r}: a scan folder name or null")
        library.folder(previous)
        if previous >= name:
            raise json_error(web.HTTPBadRequest, f"previous_scan {previous!r} is not earlier than {name!r}")
        await check_same_patient(library, name, previous)
    book = _book(folder)
    book.previous_scan = previous
    await _off_loop(write_marks, folder, book)
    return web.json_response({"previous_scan": previous})


def routes(app: web.Application) -> None:
    app[keys.CARRIERS] = Carriers()
    app.router.add_get("/api/scans/{folder}/marks", list_marks)
    app.router.add_post("/api/scans/{folder}/marks", add_mark)
    app.router.add_delete("/api/scans/{folder}/marks/{mark}", delete_mark)
    app.router.add_put("/api/scans/{folder}/previous", set_previous)
