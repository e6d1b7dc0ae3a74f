"""A scan's patient and study, checked against DICOM's value rules before anything is stored.

Every field is refused when it could not be sent to an archive as it is: control characters, a
backslash (DICOM's value separator), text that is not valid Unicode (a lone surrogate from a
mis-decoded command line), more characters than its value representation holds. A refusal names
the field and the rule, never the value: patient data stays out of error lines and logs.
Non-ASCII names are kept as text and sent as UTF-8 (Specific Character Set ``ISO_IR 192``).
"""

from __future__ import annotations

import datetime as _dt
import re
from dataclasses import asdict, dataclass
from typing import Any

from daemon.errors import DaemonError

MAX_LO = 64
"""Long String (patient id, descriptions): characters."""
MAX_PN_GROUP = 64
"""Person Name: characters of one component group."""
MAX_SH = 16
"""Short String (accession number): characters."""
UID = re.compile(r"^(0|[1-9][0-9]*)(\.(0|[1-9][0-9]*))+$")
SEXES = ("M", "F", "O")


class PatientError(DaemonError, ValueError):
    """A patient or study field is not valid; names the field and the rule (never the value)."""

    def __init__(self, field: str, problem: str) -> None:
        self.field = field
        self.problem = problem
        super().__init__(f"{field}: {problem}")


def _text(value: Any, field: str, limit: int, *, required: bool) -> str | None:
    """Printable Unicode text without backslash, trimmed; None when absent and allowed."""
    if value is None or (isinstance(value, str) and not value.strip()):
        if required:
            raise PatientError(field, "missing")
        return None
    if not isinstance(value, str):
        raise PatientError(field, f"expected text, got {type(value).__name__}")
    try:
        value.encode("utf-8")
    except UnicodeEncodeError:
        raise PatientError(field, "not valid text (undecodable bytes; give UTF-8)") from None
    value = value.strip()
    if not value.isprintable():
        raise PatientError(field, "contains control or unprintable characters")
    if "\\" in value:
        raise PatientError(field, "contains a backslash (DICOM's value separator)")
    if len(value) > limit:
        raise PatientError(field, f"{len(value)} characters; at most {limit}")
    result: str = value
    return result


def _name(value: Any) -> str:
    """A DICOM Person Name, alphabetic group only: ``Family^Given^Middle^Prefix^Suffix``."""
    name = _text(value, "patient_name", MAX_PN_GROUP, required=True)
    assert name is not None
    if "=" in name:
        raise PatientError("patient_name", "one name only: '=' starts DICOM's ideographic group")
    parts = name.split("^")
    if len(parts) > 5:
        raise PatientError("patient_name", "at most five components Family^Given^Middle^Prefix^Suffix")
    if not parts[0].strip():
        raise PatientError("patient_name", "the family name (before the first '^') is empty")
    return "^".join(p.strip() for p in parts)


def _birth_date(value: Any) -> str | None:
    """YYYYMMDD (YYYY-MM-DD accepted), a real date from 1900 on."""
    text = _text(value, "birth_date", 10, required=False)
    if text is None:
        return None
    digits = text.replace("-", "") if re.fullmatch(r"\d{4}-\d{2}-\d{2}", text) else text
    if not re.fullmatch(r"\d{8}", digits):
        raise PatientError("birth_date", "expected YYYYMMDD or YYYY-MM-DD")
    try:
        day = _dt.date(int(digits[:4]), int(digits[4:6]), int(digits[6:]))
    except ValueError:
        raise PatientError("birth_date", "not a calendar date") from None
    if day.year < 1900:
        raise PatientError("birth_date", "before 1900")
    return digits


def check_uid(value: Any, field: str) -> str | None:
    """A DICOM UID (digits and dots, no leading zeros, at most 64 characters) or None."""
    text = _text(value, field, 64, required=False)
    if text is not None and not UID.fullmatch(text):
        raise PatientError(field, "not a DICOM UID (digits and dots, no leading zeros)")
    return text


@dataclass(frozen=True)
class Patient:
    """Who a scan is of. ``name`` in DICOM Person Name form (``Family^Given``); ``birth_date``
    YYYYMMDD; ``sex`` M, F or O."""

    patient_id: str
    name: str
    birth_date: str | None = None
    sex: str | None = None

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def of(cls, patient_id: Any, name: Any, birth_date: Any = None, sex: Any = None) -> Patient:
        """Checked fields; PatientError naming the first one that is not valid."""
        pid = _text(patient_id, "patient_id", MAX_LO, required=True)
        assert pid is not None
        sex_text = _text(sex, "sex", 1, required=False)
        if sex_text is not None and sex_text.upper() not in SEXES:
            raise PatientError("sex", f"one of {', '.join(SEXES)}")
        return cls(pid, _name(name), _birth_date(birth_date), sex_text.upper() if sex_text else None)

    @classmethod
    def from_dict(cls, data: Any) -> Patient:
        if not isinstance(data, dict) or set(data) - {"patient_id", "name", "birth_date", "sex"}:
            raise PatientError("patient", "expected an object with patient_id, name, birth_date, sex")
        return cls.of(data.get("patient_id"), data.get("name"), data.get("birth_date"), data.get("sex"))


@dataclass(frozen=True)
class Study:
    """The visit a scan belongs to in DICOM terms: the Study and Series Instance UIDs (given by
    the worklist, or made once from the scan), the accession number of the clinic's order."""

    study_instance_uid: str
    series_instance_uid: str
    accession_number: str | None = None
    description: str = "Total body photography"

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: Any) -> Study:
        keys = {"study_instance_uid", "series_instance_uid", "accession_number", "description"}
        if not isinstance(data, dict) or set(data) - keys:
            raise PatientError("study", f"expected an object with {', '.join(sorted(keys))}")
        study = check_uid(data.get("study_instance_uid"), "study_instance_uid")
        series = check_uid(data.get("series_instance_uid"), "series_instance_uid")
        if study is None or series is None:
            raise PatientError("study", "study_instance_uid and series_instance_uid are required")
        return cls(study, series, accession(data.get("accession_number")),
                   _text(data.get("description"), "description", MAX_LO, required=False) or cls.description)


def accession(value: Any) -> str | None:
    return _text(value, "accession_number", MAX_SH, required=False)


@dataclass(frozen=True)
class ScanSubject:
    """What a scan request says about the patient: the patient, and what the worklist or the
    operator fixed of the study (accession number, a scheduled Study Instance UID)."""

    patient: Patient
    accession_number: str | None = None
    study_instance_uid: str | None = None

    ARGS = ("patient_id", "patient_name", "birth_date", "sex", "accession_number", "study_instance_uid")
    """The control API's ``scan`` arguments that say who the scan is of."""

    @classmethod
    def from_args(cls, args: dict[str, Any]) -> ScanSubject | None:
        """From the ``scan`` request's arguments; None when they name no patient. A study field
        without a patient is refused: a scan of nobody cannot belong to an order."""
        given = {k: args.get(k) for k in cls.ARGS if args.get(k) not in (None, "")}
        if not given:
            return None
        if "patient_id" not in given or "patient_name" not in given:
            missing = "patient_id" if "patient_id" not in given else "patient_name"
            raise PatientError(missing, "missing: a scan for a patient needs patient_id and patient_name")
        patient = Patient.of(given["patient_id"], given["patient_name"], given.get("birth_date"), given.get("sex"))
        return cls(patient, accession(given.get("accession_number")),
                   check_uid(given.get("study_instance_uid"), "study_instance_uid"))

    def study(self, scan_id: str, created_utc: str) -> Study:
        """The scan's study: the worklist's Study Instance UID, else one derived from the scan (the
        same scan always has the same UIDs, so a second export adds nothing)."""
        return Study(self.study_instance_uid or derived_uid("study", scan_id, created_utc),
                     derived_uid("series", scan_id, created_utc), self.accession_number)


def derived_uid(*parts: str) -> str:
    """A UID under pydicom's root made from ``parts`` (the same parts, the same UID)."""
    from pydicom.uid import generate_uid

    return str(generate_uid(entropy_srcs=["tbp-rig", *parts]))
