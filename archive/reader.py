"""Reading a study back from the archive by DICOMweb, so a workstation views scans without the rig
PC: QIDO-RS lists the studies, WADO-RS retrieves one, and the study becomes a scan folder in a
local cache that the viewer opens like any other (dicomweb-client).

The folder is rebuilt from what the export wrote (archive/instances.py): each VL Photographic
Image's JPEG into ``images/<camera>-a<NN>.jpg`` with its camera, capture angle index, planned and
actual angle and focus distance from the acquisition context; the Encapsulated STL as
``mesh.ply``; each Key Object Selection's mark (name and point from its description) into
``marks.json``; the patient and study into the manifest. The rig's calibration is not in the
study: the viewer places the pictures with the rig file's poses.
"""

from __future__ import annotations

import hashlib
import re
from pathlib import Path
from typing import Any

from archive.instances import ENCAPSULATED_STL, JPEG_BASELINE, KEY_OBJECT_SELECTION, VL_PHOTOGRAPHIC, ExportError
from daemon.clinic.patient import Patient, PatientError, Study
from daemon.clinic.site import Tls
from daemon.records.atomic import AtomicWriter
from daemon.records.manifest import ImageRecord, ImageStatus, Manifest, ScanEnd
from daemon.records.store import ScanFolder
from planner.rig import Rig

STUDY_FIELDS = ("PatientName", "PatientID", "PatientBirthDate", "StudyDate", "StudyTime", "AccessionNumber",
                "StudyDescription", "NumberOfStudyRelatedInstances", "StudyInstanceUID")
_MARK = re.compile(r"^(?P<name>.+) at \((?P<x>-?[\d.]+), (?P<y>-?[\d.]+), (?P<z>-?[\d.]+)\) mm$")


def client(url: str, tls: Tls | None = None) -> Any:
    """A DICOMweb client; with ``tls``, HTTPS checked against the clinic's CA."""
    import requests
    from dicomweb_client.api import DICOMwebClient

    session = requests.Session()
    if tls is not None:
        session.verify = str(tls.ca_file)
        if tls.cert_file is not None:
            session.cert = (str(tls.cert_file), str(tls.key_file)) if tls.key_file else str(tls.cert_file)
    return DICOMwebClient(url=url, session=session, timeout=120)


def _value(item: dict[str, Any], tag: str) -> Any:
    values = item.get(tag, {}).get("Value") or [None]
    value = values[0]
    return value.get("Alphabetic") if isinstance(value, dict) else value


def studies(url: str, tls: Tls | None = None) -> list[dict[str, Any]]:
    """The archive's studies (QIDO-RS), newest first: uid, patient, date, accession, instances."""
    from pydicom.datadict import tag_for_keyword

    found = client(url, tls).search_for_studies(fields=list(STUDY_FIELDS))
    out = []
    for item in found:
        row = {k: _value(item, f"{tag_for_keyword(k):08X}") for k in STUDY_FIELDS}
        out.append({"study_instance_uid": row["StudyInstanceUID"], "patient_name": row["PatientName"],
                    "patient_id": row["PatientID"], "birth_date": row["PatientBirthDate"],
                    "date": row["StudyDate"], "time": row["StudyTime"], "accession_number": row["AccessionNumber"],
                    "description": row["StudyDescription"], "instances": row["NumberOfStudyRelatedInstances"]})
    return sorted(out, key=lambda r: (r["date"] or "", r["time"] or ""), reverse=True)


def folder_name(study_uid: str, date: str | None, time: str | None) -> str:
    """The cache folder of a study: the store's ``YYYYmmdd-HHMMSS-<id>`` with an id from the UID."""
    stamp = f"{(date or '19000101')[:8]}-{(time or '000000')[:6].ljust(6, '0')}"
    return f"{stamp}-a{hashlib.sha256(study_uid.encode()).hexdigest()[:12]}"


def _context(ds: Any) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for item in ds.get("AcquisitionContextSequence", []):
        meaning = item.ConceptNameCodeSequence[0].CodeMeaning
        out[meaning] = item.TextValue if item.ValueType == "TEXT" else float(item.NumericValue)
    return out


def fetch(url: str, study_uid: str, cache: Path, rig: Rig, tls: Tls | None = None) -> Path:
    """Retrieve the study (WADO-RS) into a scan folder under ``cache``; its path. Fetched again
    only when the folder is not there yet."""
    from pydicom.encaps import generate_fragmented_frames

    from analysis.marks import MarkBook, new_mark, write_marks

    # transfer syntax "*": the instances as stored (the JPEG as the rig made it), not transcoded
    instances = client(url, tls).retrieve_study(study_uid, media_types=(("application/dicom", "*"),))
    if not instances:
        raise ExportError(url, f"study {study_uid}: no instances")
    first = instances[0]
    path = cache / folder_name(study_uid, first.get("StudyDate"), first.get("StudyTime"))
    if (path / "manifest.json").is_file():
        return path
    writer = AtomicWriter()
    (path / "images").mkdir(parents=True, exist_ok=True)
    cameras = [p.id for p in rig.phones]
    images: list[ImageRecord] = []
    marks = MarkBook()
    files: dict[str, str] = {}
    for ds in instances:
        sop = str(ds.SOPClassUID)
        if sop == VL_PHOTOGRAPHIC:
            context = _context(ds)
            camera, index = context.get("Camera"), context.get("Capture angle index")
            if camera not in cameras or index is None:
                continue
            name = f"images/{camera}-a{int(index):02d}.jpg"
            if str(ds.file_meta.TransferSyntaxUID) != JPEG_BASELINE:
                raise ExportError(url, f"{name}: the archive sent it in {ds.file_meta.TransferSyntaxUID}, "
                                       "not as the JPEG the rig made (JPEG Baseline)")
            data = b"".join(next(generate_fragmented_frames(ds.PixelData)))
            data = data[:data.rfind(b"\xff\xd9") + 2]  # the JPEG without the even-length padding
            writer.write(path / name, data)
            focus = context.get("Focus distance", float("nan"))
            images.append(ImageRecord(
                camera, cameras.index(camera), int(index), context.get("Planned beam angle", 0.0), focus,
                1000.0 / focus if focus > 0 else float("inf"), status=ImageStatus.VERIFIED,
                actual_angle_deg=context.get("Beam angle at exposure"), file=name, size_bytes=len(data),
                sha256=hashlib.sha256(data).hexdigest()))
        elif sop == ENCAPSULATED_STL:
            import io

            import trimesh

            # STL repeats each corner per triangle: merged back into one vertex each
            mesh = trimesh.load(io.BytesIO(bytes(ds.EncapsulatedDocument)), file_type="stl", process=True)
            writer.write(path / "mesh.ply", mesh.export(file_type="ply"))
            files["mesh"] = "mesh.ply"
        elif sop == KEY_OBJECT_SELECTION:
            text = next((i.TextValue for i in ds.get("ContentSequence", []) if i.ValueType == "TEXT"), "")
            match = _MARK.match(text or "")
            if match:
                marks.marks.append(new_mark(match["name"], [float(match[k]) for k in "xyz"]))
    images.sort(key=lambda i: (i.angle_index, i.camera_index))
    try:
        patient = Patient.of(first.PatientID, str(first.PatientName) or "Unnamed",
                             first.get("PatientBirthDate") or None, first.get("PatientSex") or None)
    except PatientError:
        patient = None
    study = Study(study_uid, str(first.SeriesInstanceUID), first.get("AccessionNumber") or None)
    date, time = first.get("StudyDate") or "19000101", first.get("StudyTime") or "000000"
    manifest = Manifest(scan_id=path.name.split("-", 2)[2], created_utc=f"{date[:4]}-{date[4:6]}-{date[6:8]}T"
                        f"{time[:2]}:{time[2:4]}:{time[4:6]}+00:00", rig_digest="", calibration_digest="",
                        cameras=cameras, state=ScanEnd.COMPLETE, in_progress=False, files=files,
                        patient=patient, study=study, images=images)
    ScanFolder(path, manifest, writer).save()
    if marks.marks:
        write_marks(path, marks)
    return path
