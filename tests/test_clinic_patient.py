"""A scan's patient: checked against DICOM's value rules, kept in the manifest only, in a folder
only the operators' group reads. Synthetic identities only."""

from __future__ import annotations

import json
import os
import stat
from pathlib import Path

import pytest
from hypothesis import given
from hypothesis import strategies as st

from daemon.clinic.patient import Patient, PatientError, ScanSubject, Study
from daemon.records.manifest import ManifestError
from daemon.records.store import ScanStore, read_folder
from planner.rig import load_rig

NAME = "Testperson^Synthia"
PID = "SYN-000123"


def subject(**extra: str) -> ScanSubject:
    subject = ScanSubject.from_args({"patient_id": PID, "patient_name": NAME, **extra})
    assert subject is not None
    return subject


@pytest.mark.parametrize("field, value, rule", [
    ("patient_name", "Test\x1bperson^Synthia", "control"),
    ("patient_name", "Test\nperson", "control"),
    ("patient_name", "Back\\slash", "backslash"),
    ("patient_name", "A" * 65, "at most 64"),
    ("patient_name", "Family=Ideographic", "one name only"),
    ("patient_name", "^Given", "family name"),
    ("patient_name", "a^b^c^d^e^f", "five components"),
    ("patient_name", "Bad\udcff^Bytes", "not valid text"),
    ("patient_id", "X" * 65, "at most 64"),
    ("patient_id", "\x00", "control"),
    ("birth_date", "19990231", "calendar"),
    ("birth_date", "1.1.1999", "YYYYMMDD"),
    ("birth_date", "18991231", "1900"),
    ("sex", "Q", "one of"),
    ("accession_number", "A" * 17, "at most 16"),
    ("study_instance_uid", "1.2.03", "UID"),
])
def test_hostile_patient_fields_are_refused_naming_the_field_not_the_value(field, value, rule):
    args = {"patient_id": PID, "patient_name": NAME, field: value}
    with pytest.raises(PatientError) as refused:
        ScanSubject.from_args(args)
    assert refused.value.field == field and rule in str(refused.value)
    assert value not in str(refused.value)


def test_a_study_field_without_a_patient_is_refused_and_no_patient_is_none():
    assert ScanSubject.from_args({}) is None
    with pytest.raises(PatientError, match="patient_name"):
        ScanSubject.from_args({"patient_id": PID, "accession_number": "A1"})


def test_non_ascii_names_are_kept_as_text():
    s = subject(patient_name="Müller-Łukasz^Zoë Ångström", birth_date="1980-02-29", sex="f")
    assert s.patient == Patient(PID, "Müller-Łukasz^Zoë Ångström", "19800229", "F")


@given(st.text(max_size=80))
def test_any_name_is_accepted_as_dicom_can_hold_it_or_refused(text):
    """A property of the checker: what it accepts fits a DICOM PN of one group, and a refusal
    never repeats the text."""
    try:
        patient = Patient.of(PID, text)
    except PatientError as exc:
        assert len(text.strip()) < 4 or text.strip() not in str(exc)
        return
    name = patient.name
    assert 0 < len(name) <= 64 and name.isprintable() and "\\" not in name and "=" not in name
    assert name.count("^") <= 4 and name.split("^")[0]
    name.encode("utf-8")


def test_the_study_uids_are_made_once_from_the_scan_and_a_worklist_uid_is_kept():
    made = subject().study("abc123", "2030-01-02T03:04:05+00:00")
    assert made == subject().study("abc123", "2030-01-02T03:04:05+00:00")
    assert made.study_instance_uid != subject().study("abc124", "2030-01-02T03:04:05+00:00").study_instance_uid
    assert made.study_instance_uid != made.series_instance_uid
    scheduled = subject(study_instance_uid="1.2.3.4.5", accession_number="ACC7").study("abc123", "x")
    assert scheduled.study_instance_uid == "1.2.3.4.5" and scheduled.accession_number == "ACC7"
    assert Study.from_dict(made.as_dict()) == made


def test_the_manifest_keeps_the_patient_and_refuses_a_tampered_one(tmp_path: Path):
    rig = load_rig()
    folder = ScanStore(tmp_path, reserve_bytes=0).create(rig, scan_id="p1", subject=subject(birth_date="19700101"))
    folder.finish(folder.manifest.state)
    again = read_folder(folder.path).manifest
    assert again.patient == Patient(PID, NAME, "19700101") and again.study == folder.manifest.study
    data = json.loads((folder.path / "manifest.json").read_text())
    assert data["patient"]["name"] == NAME and data["study"]["study_instance_uid"]
    data["patient"]["name"] = "Evil\x07^Bell"
    (folder.path / "manifest.json").write_text(json.dumps(data))
    with pytest.raises(ManifestError, match="patient_name: contains control"):
        read_folder(folder.path)
    nobody = ScanStore(tmp_path, reserve_bytes=0).create(rig, scan_id="p2")
    assert read_folder(nobody.path).manifest.patient is None


def test_scan_folders_are_readable_by_the_operators_group_only(tmp_path: Path):
    """Whatever the umask: the folder and images/ 0750 with the store's group (set-group-id
    store, as systemd/tbp-rig.tmpfiles makes it), files 0640."""
    root = tmp_path / "scans"
    root.mkdir()
    operators = 54321
    if os.geteuid() == 0:
        os.chown(root, -1, operators)
    else:
        operators = root.stat().st_gid
    os.chmod(root, 0o2750)
    old = os.umask(0)
    try:
        folder = ScanStore(root, reserve_bytes=0).create(load_rig(), scan_id="p3", subject=subject())
        folder.finish(folder.manifest.state)
    finally:
        os.umask(old)
    for path in (folder.path, folder.path / "images"):
        mode = path.stat().st_mode
        assert stat.S_IMODE(mode) & 0o777 == 0o750, oct(mode)
        assert mode & stat.S_ISGID and path.stat().st_gid == operators
    manifest = folder.path / "manifest.json"
    assert stat.S_IMODE(manifest.stat().st_mode) == 0o640 and manifest.stat().st_gid == operators
