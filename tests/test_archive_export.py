"""`tbp export` against a real archive (Debian's Orthanc with DICOMweb, on loopback): one study per
scan over C-STORE and STOW-RS, a second export adds nothing, refusals name the peer and the reason,
dicom3tools' dciodvfy finds no error in any kind of instance, and a de-identified export holds
none of the patient's identity. Synthetic identities only."""

from __future__ import annotations

import io
import shutil
import subprocess
from pathlib import Path

import pytest

from analysis.marks import MarkBook, new_mark, write_marks
from daemon.clinic.patient import Patient
from daemon.records.store import read_folder
from tests.dicom_services import free_port, need, orthanc

pytestmark = pytest.mark.slow

NAME, PID = "Müller-Testperson^Zoë", "SYN-ÄRCHIVE-1"
KINDS = {"1.2.840.10008.5.1.4.1.1.77.1.4": "image", "1.2.840.10008.5.1.4.1.1.104.3": "mesh",
         "1.2.840.10008.5.1.4.1.1.88.59": "mark", "1.2.840.10008.5.1.4.1.1.88.11": "report"}


@pytest.fixture(scope="module")
def scan(web_store: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The shared simulated scan for a non-ASCII synthetic patient, with one lesion mark."""
    store = tmp_path_factory.mktemp("export")
    source = next(p for p in web_store.iterdir() if p.is_dir())
    folder = store / source.name
    shutil.copytree(source, folder)
    scan = read_folder(folder)
    scan.manifest.patient = Patient.of(PID, NAME, "19700101", "F")
    scan.save()
    mesh = scan.read_mesh()
    write_marks(folder, MarkBook([new_mark("naevus", mesh.vertices[int(mesh.vertices[:, 0].argmax())].tolist())]))
    return folder


def export(scan: Path, *args: str) -> subprocess.CompletedProcess[str]:
    import contextlib

    from cli import main

    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main(["export", str(scan), *args])
    return subprocess.CompletedProcess([], code, out.getvalue(), err.getvalue())


def _study(server, uid: str) -> dict[str, list[dict]]:
    by_kind: dict[str, list[dict]] = {}
    for instance in server.instances_of(uid):
        tags = server.get(f"/instances/{instance['ID']}/simplified-tags")
        by_kind.setdefault(KINDS[tags["SOPClassUID"]], []).append({**tags, "ID": instance["ID"]})
    return by_kind


def test_export_over_c_store_is_one_complete_study_and_a_second_export_adds_nothing(scan: Path, tmp_path: Path):
    import pydicom
    from pydicom.encaps import generate_fragmented_frames

    manifest = read_folder(scan).manifest
    verified = [i for i in manifest.images if i.status.value == "verified"]
    with orthanc(tmp_path / "orthanc") as server:
        pacs = ["--pacs", f"127.0.0.1:{server.dicom_port}", "--called-aet", "ORTHANC", "--calling-aet", "TBPRIG1"]
        first = export(scan, *pacs)
        assert first.returncode == 0, first.stderr
        study = _study(server, manifest.study.study_instance_uid)
        assert {k: len(v) for k, v in study.items()} == {"image": len(verified), "mesh": 1, "mark": 1, "report": 1}
        assert len(server.get("/studies")) == 1
        image = study["image"][0]
        assert image["PatientName"] == NAME and image["PatientID"] == PID and image["PatientBirthDate"] == "19700101"
        stored = pydicom.dcmread(io.BytesIO(_raw(server, image["ID"])))
        assert stored.file_meta.TransferSyntaxUID == "1.2.840.10008.1.2.4.50"
        jpeg = b"".join(next(generate_fragmented_frames(stored.PixelData)))
        files = [(scan / i.file).read_bytes() for i in verified]
        assert any(jpeg in (data, data + b"\0") for data in files)  # the JPEG unchanged (padded to even length)
        context = {item.ConceptNameCodeSequence[0].CodeMeaning: item for item in stored.AcquisitionContextSequence}
        assert {"Camera", "Beam angle at exposure", "Focus distance", "Pixel size at focus distance",
                "Camera position x (rig frame)", "Optical axis z (rig frame)"} <= set(context)
        flags = {i["RecognizableVisualFeatures"] for i in study["image"]}
        assert flags == {"YES", "NO"}  # the face is in some pictures, not in all
        uids = sorted(i["SOPInstanceUID"] for kind in study.values() for i in kind)

        second = export(scan, *pacs)
        assert second.returncode == 0, second.stderr
        again = _study(server, manifest.study.study_instance_uid)
        assert sorted(i["SOPInstanceUID"] for kind in again.values() for i in kind) == uids
        assert len(server.get("/instances")) == len(uids)


def _raw(server, instance_id: str) -> bytes:
    import urllib.request

    with urllib.request.urlopen(f"{server.url}/instances/{instance_id}/file", timeout=30) as answer:
        return answer.read()


def test_export_over_stow_rs_and_de_identified(scan: Path, tmp_path: Path):
    manifest = read_folder(scan).manifest
    with orthanc(tmp_path / "orthanc") as server:
        assert export(scan, "--dicomweb", server.dicomweb).returncode == 0
        study = _study(server, manifest.study.study_instance_uid)
        assert {k: len(v) for k, v in study.items()}["mesh"] == 1 and len(study["image"]) >= 300
        total = len(server.get("/instances"))
        deid = export(scan, "--dicomweb", server.dicomweb, "--deidentify")
        assert deid.returncode == 0, deid.stderr
        assert export(scan, "--dicomweb", server.dicomweb, "--deidentify").returncode == 0
        assert len(server.get("/instances")) == 2 * total  # the de-identified study once
        other = [s for s in server.studies() if s["MainDicomTags"]["StudyInstanceUID"] != manifest.study.study_instance_uid]
        (anonymous,) = other
        files = [_raw(server, i["ID"]) for i in server.get(f"/studies/{anonymous['ID']}/instances")]
    secrets = [NAME.encode(), "Müller".encode(), PID.encode(), b"19700101", manifest.study.study_instance_uid.encode(),
               manifest.scan_id.encode(), b"naevus"]
    for data in files:
        for secret in secrets:
            assert secret not in data, secret
    import pydicom

    first = pydicom.dcmread(io.BytesIO(files[0]))
    assert first.PatientIdentityRemoved == "YES" and first.DeidentificationMethodCodeSequence[0].CodeValue == "113100"


def test_refusals_name_the_peer_and_the_reason(scan: Path, tmp_path: Path):
    with orthanc(tmp_path / "orthanc") as server:
        wrong = export(scan, "--pacs", f"127.0.0.1:{server.dicom_port}", "--called-aet", "NOTORTHANC")
    assert wrong.returncode == 1
    assert f"NOTORTHANC@127.0.0.1:{server.dicom_port}: association rejected" in wrong.stderr
    assert "Called AE title not recognised" in wrong.stderr
    port = free_port()
    absent = export(scan, "--pacs", f"127.0.0.1:{port}", "--called-aet", "PACS")
    assert absent.returncode == 1 and f"PACS@127.0.0.1:{port}: no association" in absent.stderr
    bad = export(scan, "--pacs", "127.0.0.1:104", "--called-aet", "BAD\\AET")
    assert bad.returncode == 2 and "--called-aet" in bad.stderr
    nobody = tmp_path / "nobody"
    shutil.copytree(scan, nobody)
    folder = read_folder(nobody)
    folder.manifest.patient = None
    folder.save()
    refused = export(nobody, "--out", str(tmp_path / "files"))
    assert refused.returncode == 2 and "for no patient" in refused.stderr


def test_dciodvfy_finds_no_error_in_any_kind_of_instance(scan: Path, tmp_path: Path):
    dciodvfy = need("dciodvfy")
    for mode in ((), ("--deidentify",)):
        out = tmp_path / ("deid" if mode else "plain")
        assert export(scan, "--out", str(out), *mode).returncode == 0
        files = sorted(out.iterdir())
        by_kind = {}
        for path in files:
            by_kind.setdefault(path.stem.split("-", 1)[1], path)
        assert set(by_kind) == {"image", "mesh", "mark", "report"}
        for kind, path in by_kind.items():
            answer = subprocess.run([dciodvfy, str(path)], capture_output=True, text=True, timeout=120)
            errors = [line for line in (answer.stdout + answer.stderr).splitlines() if line.startswith("Error")]
            assert errors == [], (kind, mode, errors)
