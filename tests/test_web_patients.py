"""The viewer's patients: visits grouped by patient, and "compare with an earlier scan" offering and
accepting only the same patient's visits (another person's scan is a wrong-patient finding).
Synthetic identities only."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from analysis.marks import MarkBook, write_marks
from daemon.clinic.patient import Patient
from daemon.records.store import read_folder
from tests.test_web import client_for, folder_of


def _visit(store: Path, source: str, stamp: str, patient: Patient | None) -> str:
    name = f"{stamp}-" + source.split("-", 2)[2]
    shutil.copytree(store / source, store / name)
    folder = read_folder(store / name)
    folder.manifest.patient = patient
    folder.save()
    return name


@pytest.fixture
def clinic_store(web_store: Path, tmp_path: Path) -> tuple[Path, dict[str, str]]:
    """The shared scan (patient SYN-0001) and later visits: the same patient, another one, nobody."""
    store = tmp_path / "store"
    shutil.copytree(web_store, store)
    first = folder_of(store)
    same = read_folder(store / first).manifest.patient
    names = {
        "first": first,
        "later": _visit(store, first, "20990101-000000", same),
        "other": _visit(store, first, "20990201-000000", Patient.of("SYN-0002", "Otherperson^Ada")),
        "nobody": _visit(store, first, "20990301-000000", None),
        "latest": _visit(store, first, "20990401-000000", same),
    }
    return store, names


async def test_patients_list_their_visits_and_compare_offers_only_the_same_patient(clinic_store):
    store, n = clinic_store
    client = await client_for(store)
    try:
        listed = await (await client.get("/api/patients")).json()
        by_id = {p["patient_id"]: [v["folder"] for v in p["visits"]] for p in listed["patients"]}
        assert by_id == {"SYN-0001": [n["latest"], n["later"], n["first"]], "SYN-0002": [n["other"]]}
        assert listed["without_patient"] == [n["nobody"]]
        assert [p["name"] for p in listed["patients"]] == ["Otherperson^Ada", "Testperson^Capsule"]

        earlier = await (await client.get(f"/api/scans/{n['latest']}/earlier")).json()
        assert earlier["patient"]["patient_id"] == "SYN-0001"
        assert [v["folder"] for v in earlier["visits"]] == [n["later"], n["first"]]
        alone = await (await client.get(f"/api/scans/{n['other']}/earlier")).json()
        assert alone["visits"] == []
        nobody = await (await client.get(f"/api/scans/{n['nobody']}/earlier")).json()
        assert nobody["patient"] is None and nobody["visits"] == [] and "no patient" in nobody["note"]

        put = lambda later, earlier: client.put(f"/api/scans/{later}/previous", json={"previous_scan": earlier})  # noqa: E731
        refused = await put(n["latest"], n["other"])
        assert refused.status == 400 and "not a scan of this scan's patient" in (await refused.json())["error"]["message"]
        assert (await put(n["latest"], n["nobody"])).status == 400
        assert (await put(n["nobody"], n["first"])).status == 400
        assert (await put(n["latest"], n["first"])).status == 200
        assert not (store / n["other"] / "marks.json").exists()
        detail = await (await client.get(f"/api/scans/{n['latest']}")).json()
        assert detail["patient"]["name"] == "Testperson^Capsule" and detail["study"]["study_instance_uid"]
    finally:
        await client.close()


async def test_a_marks_file_naming_another_patients_scan_carries_nothing(clinic_store):
    """marks.json edited by hand (or copied) to name another patient's scan: the marks list says
    so and carries none of that scan's marks."""
    store, n = clinic_store
    from analysis.marks import new_mark

    write_marks(store / n["other"], MarkBook([new_mark("naevus", [0.0, 0.0, 900.0])]))
    shutil.copytree(store / n["other"], store / ("20990501-000000-" + n["first"].split("-", 2)[2]))
    later = "20990501-000000-" + n["first"].split("-", 2)[2]
    folder = read_folder(store / later)
    folder.manifest.patient = Patient.of("SYN-0001", "Testperson^Capsule")
    folder.save()
    write_marks(store / later, MarkBook(previous_scan=n["other"]))
    client = await client_for(store)
    try:
        listed = await (await client.get(f"/api/scans/{later}/marks")).json()
        assert listed["carried"] == [] and "not a scan of this scan's patient" in listed["registration"]["error"]
    finally:
        await client.close()
