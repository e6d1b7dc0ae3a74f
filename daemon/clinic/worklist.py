"""The clinic's Modality Worklist: today's scheduled total body photographs, asked for by C-FIND.

Each answer becomes a :class:`WorklistItem` whose patient passed the same checks as a typed one
(daemon/clinic/patient.py); an answer that does not is left out and counted in ``problems``,
naming the item and the field, never the value. Picking an item starts the scan with its
patient, accession number and the Study Instance UID the RIS scheduled.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from daemon.clinic.dimse import associate, check_status
from daemon.clinic.patient import PatientError, ScanSubject, accession, check_uid
from daemon.clinic.site import Site, WorklistSource

WORKLIST_FIND = "1.2.840.10008.5.1.4.31"
"""Modality Worklist Information Model - FIND."""
MAX_ITEMS = 200


@dataclass(frozen=True)
class WorklistItem:
    """One scheduled procedure step, its patient checked."""

    subject: ScanSubject
    procedure: str | None
    scheduled: str | None
    """YYYYMMDD HHMM (the RIS's local time) when given."""

    def as_dict(self) -> dict[str, Any]:
        p = self.subject.patient
        return {"patient_id": p.patient_id, "patient_name": p.name, "birth_date": p.birth_date, "sex": p.sex,
                "accession_number": self.subject.accession_number,
                "study_instance_uid": self.subject.study_instance_uid,
                "procedure": self.procedure, "scheduled": self.scheduled}


@dataclass
class Worklist:
    items: list[WorklistItem] = field(default_factory=list)
    problems: list[str] = field(default_factory=list)

    def as_dict(self) -> dict[str, Any]:
        return {"items": [i.as_dict() for i in self.items], "problems": list(self.problems)}


def query(source: WorklistSource, site: Site, date: str | None = None) -> Worklist:
    """C-FIND the provider for the steps of ``source.modality`` (on ``source.station_aet`` when
    set) scheduled on ``date`` (YYYYMMDD; None: any day). Blocking: run it in a thread.

    Raises the DicomPeerError of daemon/clinic/dimse.py naming the provider and the reason."""
    from pydicom.dataset import Dataset
    from pydicom.uid import ExplicitVRLittleEndian, ImplicitVRLittleEndian

    ask = Dataset()
    ask.SpecificCharacterSet = "ISO_IR 192"  # asks for the answers' character set; names are decoded by it
    for keyword in ("PatientName", "PatientID", "PatientBirthDate", "PatientSex", "AccessionNumber",
                    "StudyInstanceUID", "RequestedProcedureDescription", "RequestedProcedureID"):
        setattr(ask, keyword, "")
    step = Dataset()
    step.Modality = source.modality
    step.ScheduledStationAETitle = source.station_aet or ""
    step.ScheduledProcedureStepStartDate = date or ""
    step.ScheduledProcedureStepStartTime = ""
    step.ScheduledProcedureStepDescription = ""
    ask.ScheduledProcedureStepSequence = [step]
    peer = source.peer
    assoc = associate(site.ae_title, peer, [(WORKLIST_FIND, [ExplicitVRLittleEndian, ImplicitVRLittleEndian])],
                      tls=site.tls)
    answers: list[Any] = []
    try:
        for status, identifier in assoc.send_c_find(ask, WORKLIST_FIND):
            code = check_status(peer, status, "worklist C-FIND")
            if code in (0xFF00, 0xFF01) and identifier is not None and len(answers) < MAX_ITEMS:
                answers.append(identifier)
    finally:
        if assoc.is_established:
            assoc.release()
    worklist = Worklist()
    for n, answer in enumerate(answers, 1):
        try:
            worklist.items.append(item_of(answer))
        except PatientError as exc:
            worklist.problems.append(f"worklist item {n} left out: {exc}")
        except (AttributeError, TypeError, ValueError, KeyError) as exc:
            worklist.problems.append(f"worklist item {n} left out: malformed answer ({type(exc).__name__})")
    return worklist


def _text(ds: Any, keyword: str, field: str | None = None) -> str | None:
    """The value as text. Without a Specific Character Set an answer is in DICOM's default
    repertoire (ASCII): other bytes there are a provider's wrong character set, refused (decoded as
    Latin-1 they would make another name)."""
    value = ds.get(keyword)
    if value is None or value == "":
        return None
    text = str(value)
    if not text.isascii() and not ds.get("SpecificCharacterSet"):
        raise PatientError(field or keyword, "non-ASCII text in an answer that names no character set "
                                             "(Specific Character Set): the provider's encoding is unknown")
    return text


def item_of(answer: Any) -> WorklistItem:
    """A worklist answer's item; PatientError naming the field that is not valid."""
    subject = ScanSubject.from_args({
        "patient_id": _text(answer, "PatientID", "patient_id"),
        "patient_name": _text(answer, "PatientName", "patient_name"),
        "birth_date": _text(answer, "PatientBirthDate", "birth_date"), "sex": _text(answer, "PatientSex", "sex"),
    })
    if subject is None:
        raise PatientError("patient_id", "missing in the worklist answer")
    steps = answer.get("ScheduledProcedureStepSequence") or []
    step = steps[0] if len(steps) else None
    when = None
    if step is not None and _text(step, "ScheduledProcedureStepStartDate"):
        when = f"{_text(step, 'ScheduledProcedureStepStartDate')} {(_text(step, 'ScheduledProcedureStepStartTime') or '')[:4]}"
    procedure = _text(answer, "RequestedProcedureDescription") or (
        _text(step, "ScheduledProcedureStepDescription") if step is not None else None)
    return WorklistItem(
        ScanSubject(subject.patient, accession(_text(answer, "AccessionNumber", "accession_number")),
                    check_uid(_text(answer, "StudyInstanceUID"), "study_instance_uid")),
        None if procedure is None else procedure[:64].strip() if procedure.isprintable() else None,
        when.strip() if when else None,
    )
