"""Patients and their visits, as the viewer lists them: every scan for a patient is a visit, and
only the same patient's earlier visits are offered to compare with (a scan of another person
carried onto this body would be a wrong-patient finding).

A patient is known by the clinic's patient id in the scans' manifests; the store keeps no other
list of patients.
"""

from __future__ import annotations

from typing import Any

from aiohttp import web

from daemon.clinic.patient import Patient
from web import keys
from web.scans import ScanLibrary, _off_loop, json_error


def _library(request: web.Request) -> ScanLibrary:
    return request.app[keys.LIBRARY]


def group_by_patient(rows: list[dict[str, Any]]) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """(patients, scans without a patient) from the scan list's rows (newest first): each patient
    with the name and birth date of their latest visit and every visit, newest first."""
    patients: dict[str, dict[str, Any]] = {}
    nobody = []
    for row in rows:
        patient = row.get("patient")
        if not patient:
            nobody.append(row)
            continue
        entry = patients.setdefault(patient["patient_id"], {**patient, "visits": []})
        entry["visits"].append({k: row.get(k) for k in (
            "folder", "scan_id", "created_utc", "state", "in_progress", "reason", "missing", "counts", "has_mesh",
            "report", "marks", "sharp_skin", "accession_number")})
    ordered = sorted(patients.values(), key=lambda p: (p["name"].casefold(), p["patient_id"]))
    return ordered, nobody


def same_patient(a: Patient | None, b: Patient | None) -> bool:
    """Both scans are of one patient (a scan without a patient is nobody's: never the same)."""
    return a is not None and b is not None and a.patient_id == b.patient_id


async def list_patients(request: web.Request) -> web.Response:
    rows = await _off_loop(_library(request).listing)
    patients, nobody = group_by_patient(rows)
    return web.json_response({"patients": patients, "without_patient": [r["folder"] for r in nobody]})


async def earlier_visits(request: web.Request) -> web.Response:
    """The visits this scan may be compared with: the same patient's earlier scans with a body."""
    library = _library(request)
    name = request.match_info["folder"]
    patient = await _off_loop(library.patient_of, name)
    if patient is None:
        return web.json_response({"patient": None, "visits": [],
                                  "note": "this scan is for no patient: only scans of one patient are compared"})
    rows = await _off_loop(library.listing)
    visits = [r for r in rows if r.get("patient") and r["patient"]["patient_id"] == patient.patient_id
              and r["folder"] < name and r.get("has_mesh")]
    return web.json_response({"patient": patient.as_dict(), "visits": visits})


async def check_same_patient(library: ScanLibrary, later: str, earlier: str) -> None:
    """400 unless ``earlier`` is a scan of ``later``'s patient."""
    a, b = await _off_loop(library.patient_of, later), await _off_loop(library.patient_of, earlier)
    if a is None:
        raise json_error(web.HTTPBadRequest, "this scan is for no patient: only scans of one patient are compared")
    if not same_patient(a, b):
        raise json_error(web.HTTPBadRequest, f"{earlier[:80]!r} is not a scan of this scan's patient")


def routes(app: web.Application) -> None:
    app.router.add_get("/api/patients", list_patients)
    app.router.add_get("/api/scans/{folder}/earlier", earlier_visits)
