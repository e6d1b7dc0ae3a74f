"""De-identified export: DICOM PS3.15 Annex E, Basic Application Level Confidentiality Profile,
applied to the attributes this export writes (archive/instances.py), for research and sharing.

* Patient's Name and ID: a pseudonym made from the study (the same study, the same pseudonym;
  two studies of one patient are not linked); birth date, sex, accession number, study id,
  referring physician: empty (Z); descriptions and comments: removed (X); dates and times: a
  dummy (D: 19000101 000000); device serial number: a dummy (D).
* Every UID that names an instance, series, study or frame of reference: replaced (U) by one
  derived from it, consistently inside the study (a mark's reference to its image follows), and
  stably, so a second de-identified export adds nothing.
* The phone's JPEG keeps its pixels unchanged; its metadata segments (APP1-APP13, APP15: Exif,
  XMP, maker notes: capture time, device serials) and comments are dropped.
* Faces: every image where the face may be seen keeps Recognizable Visual Features YES (the
  Clean Recognizable Visual Features option is not applied: the flag tells the recipient).
* The marks' free-text names are replaced by their number; the QA report's text is the rig's own
  (counts and angles) without the scan id.

Patient Identity Removed YES and the De-identification Method (code 113100, Basic Application
Confidentiality Profile) are recorded in every instance.
"""

from __future__ import annotations

import hashlib
from dataclasses import replace
from typing import Any

from archive.instances import Instance, StudyBuilder
from daemon.clinic.patient import derived_uid

DUMMY_DATE, DUMMY_TIME = "19000101", "000000"
EMPTIED = ("PatientBirthDate", "PatientSex", "AccessionNumber", "StudyID", "ReferringPhysicianName",
           "PatientOrientation", "DocumentTitle")
REMOVED = ("StudyDescription", "SeriesDescription", "ImageComments")
UID_KEYWORDS = ("StudyInstanceUID", "SeriesInstanceUID", "SOPInstanceUID", "ReferencedSOPInstanceUID",
                "FrameOfReferenceUID", "MediaStorageSOPInstanceUID")
KEPT_APP = (0xE0, 0xEE)
"""JFIF (APP0) and Adobe (APP14, the colour transform): needed to read the pixels as they are."""


def new_uid(uid: str) -> str:
    return derived_uid("deidentified", uid)


def strip_jpeg_metadata(data: bytes) -> bytes:
    """The JPEG with its APPn segments other than APP0/APP14 and its comments removed; the frame
    header, tables and entropy-coded pixels unchanged."""
    if data[:2] != b"\xff\xd8":
        raise ValueError("not a JPEG (no SOI)")
    out = bytearray(b"\xff\xd8")
    at = 2
    while at + 4 <= len(data):
        if data[at] != 0xFF:
            raise ValueError(f"JPEG marker expected at byte {at}")
        marker = data[at + 1]
        if marker == 0xFF:  # fill byte
            at += 1
            continue
        if marker == 0xDA:  # start of scan: the rest is pixels and EOI
            out += data[at:]
            return bytes(out)
        length = int.from_bytes(data[at + 2:at + 4], "big")
        segment = data[at:at + 2 + length]
        if not ((0xE0 <= marker <= 0xEF and marker not in KEPT_APP) or marker == 0xFE):
            out += segment
        at += 2 + length
    raise ValueError("JPEG without a start of scan")


def _walk(ds: Any) -> None:
    """U: replace every instance, series, study and frame UID, in nested sequences too."""
    for element in ds:
        if element.VR == "SQ":
            for item in element.value:
                _walk(item)
        elif element.keyword in UID_KEYWORDS and element.value:
            element.value = new_uid(str(element.value))


def deidentify_dataset(ds: Any, pseudonym: str) -> Any:
    """The Basic Profile's actions on one dataset of this export (in place; returned)."""
    from pydicom.dataset import Dataset

    ds.PatientName = pseudonym
    ds.PatientID = pseudonym
    for keyword in EMPTIED:
        if keyword in ds:
            setattr(ds, keyword, "")
    for keyword in REMOVED:
        if keyword in ds:
            delattr(ds, keyword)
    for element in ds.iterall():
        if element.VR == "DA" and element.value:
            element.value = DUMMY_DATE
        elif element.VR == "TM" and element.value:
            element.value = DUMMY_TIME
        elif element.VR == "DT" and element.value:
            element.value = DUMMY_DATE + DUMMY_TIME
    if "DeviceSerialNumber" in ds:
        ds.DeviceSerialNumber = "DEIDENTIFIED"
    _walk(ds)
    if "PixelData" in ds and ds.SOPClassUID == "1.2.840.10008.5.1.4.1.1.77.1.4":
        from pydicom.encaps import encapsulate, generate_fragmented_frames

        frames = [b"".join(f) for f in generate_fragmented_frames(ds.PixelData)]
        ds.PixelData = encapsulate([strip_jpeg_metadata(frames[0])])
        ds["PixelData"].VR = "OB"
        ds["PixelData"].is_undefined_length = True  # encapsulated: items, then a sequence delimiter
    ds.PatientIdentityRemoved = "YES"
    ds.LongitudinalTemporalInformationModified = "REMOVED"
    ds.DeidentificationMethod = "PS3.15 E Basic Application Level Confidentiality Profile"
    method = Dataset()
    method.CodeValue, method.CodingSchemeDesignator = "113100", "DCM"
    method.CodeMeaning = "Basic Application Confidentiality Profile"
    ds.DeidentificationMethodCodeSequence = [method]
    return ds


def deidentified(builder: StudyBuilder) -> list[Instance]:
    """The study's instances de-identified: new UIDs, and each dataset through
    :func:`deidentify_dataset` as it is made."""
    pseudonym = "ANON-" + hashlib.sha256(builder.study.study_instance_uid.encode()).hexdigest()[:12].upper()
    out = []
    marks = {m.id: n for n, m in enumerate(builder.marks(), 1)}
    builder.report_scan_id = False
    for instance in builder.instances():
        make = instance.make
        if instance.kind == "mark":
            mark = next(m for m in builder.marks() if m.id == instance.name)
            number = marks[mark.id]
            make = lambda mark=mark, number=number: builder.mark_dataset(mark, number, f"mark {number}")  # noqa: E731
        out.append(replace(instance, sop_instance_uid=new_uid(instance.sop_instance_uid),
                           make=lambda make=make: deidentify_dataset(make(), pseudonym)))
    return out
