"""The clinic's worklist (dcmtk's wlmscpfs on loopback) and the site file. Synthetic identities only."""

from __future__ import annotations

from datetime import datetime
from pathlib import Path
from typing import Any

import pytest

from daemon.clinic.dimse import AssociationRejected, PeerUnreachable
from daemon.clinic.site import SiteConfigError, site_from_mapping
from daemon.clinic.worklist import query
from tests.dicom_services import free_port, worklist_provider, write_worklist_item


def site_for(port: int, called: str = "RISWL", **extra: Any) -> Any:
    return site_from_mapping({"ae_title": "TBPRIG1",
                              "worklist": {"host": "127.0.0.1", "port": port, "called_aet": called, **extra}})


@pytest.mark.slow
def test_the_worklist_lists_scheduled_patients_and_leaves_out_malformed_answers(tmp_path: Path):
    with worklist_provider(tmp_path) as (port, folder):
        write_worklist_item(folder, PatientName="Testperson^Wanda", PatientID="SYN-0100", PatientBirthDate="19800101",
                            AccessionNumber="ACC100", StudyInstanceUID="1.2.3.100")
        write_worklist_item(folder, PatientName="Müller^Zoë", PatientID="SYN-0101")
        write_worklist_item(folder, PatientName="Bell\x07^Ringer", PatientID="SYN-0102")
        write_worklist_item(folder, PatientName="Elsewhere^Eve", PatientID="SYN-0103", Modality="CT")
        site = site_for(port)
        answer = query(site.worklist, site)
    items = {i.subject.patient.patient_id: i for i in answer.items}
    assert sorted(items) == ["SYN-0100", "SYN-0101"]
    wanda = items["SYN-0100"]
    assert (wanda.subject.patient.name, wanda.subject.patient.birth_date) == ("Testperson^Wanda", "19800101")
    assert (wanda.subject.accession_number, wanda.subject.study_instance_uid) == ("ACC100", "1.2.3.100")
    assert items["SYN-0101"].subject.patient.name == "Müller^Zoë"
    (problem,) = answer.problems
    assert "patient_name: contains control" in problem and "Bell" not in problem


@pytest.mark.slow
def test_a_provider_sending_names_in_an_unnamed_character_set_is_refused_item_by_item(tmp_path: Path):
    with worklist_provider(tmp_path, keep_charset=False) as (port, folder):
        write_worklist_item(folder, PatientName="Müller^Zoë", PatientID="SYN-0101")
        write_worklist_item(folder, PatientName="Plain^Ascii", PatientID="SYN-0104")
        site = site_for(port)
        answer = query(site.worklist, site)
    assert [i.subject.patient.name for i in answer.items] == ["Plain^Ascii"]
    (problem,) = answer.problems
    assert "no character set" in problem and "Müller" not in problem and "MÃ" not in problem


@pytest.mark.slow
def test_a_refused_or_absent_provider_is_named_with_the_reason(tmp_path: Path):
    with worklist_provider(tmp_path) as (port, _folder):
        site = site_for(port, called="NOTRISWL")
        with pytest.raises(AssociationRejected) as rejected:
            query(site.worklist, site)
    assert str(rejected.value).startswith(f"NOTRISWL@127.0.0.1:{port}: association rejected")
    assert "Called AE title not recognised" in str(rejected.value) and not rejected.value.retry
    site = site_for(free_port())
    with pytest.raises(PeerUnreachable, match="RISWL@127.0.0.1:[0-9]+: no association"):
        query(site.worklist, site)


@pytest.mark.parametrize("raw, key", [
    ({"worklist": {}}, "ae_title"),
    ({"ae_title": "TBP\\RIG"}, "ae_title"),
    ({"ae_title": "A" * 17}, "ae_title"),
    ({"ae_title": "TBP", "printer": {}}, "printer"),
    ({"ae_title": "TBP", "worklist": {"host": "h", "port": 0, "called_aet": "W"}}, "worklist.port"),
    ({"ae_title": "TBP", "worklist": {"host": "h", "port": 104, "called_aet": "W", "colour": 1}}, "worklist.colour"),
    ({"ae_title": "TBP", "archive": {}}, "archive"),
    ({"ae_title": "TBP", "archive": {"dicomweb": "ftp://x", }}, "archive.dicomweb"),
    ({"ae_title": "TBP", "archive": {"dicomweb": "http://x", "pacs": {"host": "h", "port": 1, "called_aet": "P"}}},
     "archive"),
    ({"ae_title": "TBP", "archive": {"dicomweb": "http://x", "retry": {"first_s": 100, "max_s": 10}}},
     "archive.retry.max_s"),
])
def test_a_bad_site_file_is_refused_naming_the_key(raw, key):
    with pytest.raises(SiteConfigError) as refused:
        site_from_mapping(raw, "/etc/tbp-rig/site.yaml")
    assert refused.value.key == key and str(refused.value).startswith("/etc/tbp-rig/site.yaml: ")


class _ServiceStub:
    """The console's side of RigService: the site file, the worklist, and scans asked for."""

    def __init__(self, site: Any) -> None:
        from daemon.server.service import RigService

        self.site = site
        self.started: list[dict[str, Any]] = []
        self.worklist = lambda: RigService.worklist(self)  # the daemon's own method
        self.controller = type("C", (), {"rig": type("R", (), {"n_poses": 336})()})()

    async def scan(self, **args: Any) -> dict[str, Any]:
        from daemon.clinic.patient import ScanSubject

        ScanSubject.from_args(args)
        self.started.append(args)
        return {"scan_id": "x", "state": "PREPARING"}


@pytest.mark.slow
async def test_the_console_picks_a_worklist_patient_and_starts_the_scan_for_them(tmp_path: Path, web_store: Path):
    from tests.test_web import client_for

    with worklist_provider(tmp_path / "wl") as (port, folder):
        write_worklist_item(folder, PatientName="Testperson^Wanda", PatientID="SYN-0100",
                            StudyInstanceUID="1.2.3.100", AccessionNumber="ACC100",
                            ScheduledProcedureStepStartDate=f"{datetime.now().astimezone():%Y%m%d}")
        service = _ServiceStub(site_for(port))
        client = await client_for(web_store, service=service)
        try:
            assert (await (await client.get("/api/config")).json())["worklist"] is True
            listed = await (await client.get("/api/rig/worklist")).json()
            (item,) = listed["items"]
            pick = {k: v for k, v in item.items() if k not in ("procedure", "scheduled")}
            assert (await client.post("/api/rig/scan", json=pick)).status == 200
            hostile = await client.post("/api/rig/scan", json={**pick, "patient_name": "X\x1b[2J^Y"})
            assert hostile.status == 400 and "patient_name" in (await hostile.json())["error"]["message"]
        finally:
            await client.close()
    assert service.started == [{k: v for k, v in pick.items() if v is not None}]
    assert service.started[0]["study_instance_uid"] == "1.2.3.100"
