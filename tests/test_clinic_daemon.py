"""The daemon's side of the clinic, as its own process: a scan started for a patient keeps the
patient in its manifest and nowhere else (the daemon's log lines at debug level are searched for
the synthetic name and id). Synthetic identities only."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from tests.daemon_rigs import sparse_rig_file
from tests.sim_daemons import SimDaemon

pytestmark = pytest.mark.slow

PATIENT_ID = "SYN-LOGCHECK-4711"
FAMILY, GIVEN = "Nevershown", "Quintessa"


def test_a_scan_for_a_patient_keeps_them_in_the_manifest_and_out_of_the_logs(tmp_path: Path):
    # A scan's patient, folder and logs, not its pictures: two per speed sector.
    daemon = SimDaemon(tmp_path / "rig", log_level="debug", rig=sparse_rig_file(tmp_path / "config"))
    try:
        folder = daemon.scan("--patient-id", PATIENT_ID, "--patient-name", f"{FAMILY}^{GIVEN}",
                             "--birth-date", "1975-06-30", "--accession-number", "ACC4711")
        refused = daemon.tbp("scan", "--patient-id", PATIENT_ID, "--patient-name", f"{FAMILY}\x07^{GIVEN}")
    finally:
        assert daemon.stop() == 0
    manifest = json.loads((folder / "manifest.json").read_text())
    assert manifest["state"] == "complete"
    assert manifest["patient"] == {"patient_id": PATIENT_ID, "name": f"{FAMILY}^{GIVEN}", "birth_date": "19750630",
                                   "sex": None}
    assert manifest["study"]["accession_number"] == "ACC4711" and manifest["study"]["study_instance_uid"]
    assert refused.returncode == 2 and "patient_name: contains control" in refused.stderr
    logs = daemon.logs() + daemon.cli_output
    assert "scan_stored" in logs and "control_command" in logs  # the lines were captured
    for secret in (PATIENT_ID, FAMILY, GIVEN, "ACC4711", "19750630", manifest["study"]["study_instance_uid"]):
        assert secret not in logs, secret
    assert oct(folder.stat().st_mode & 0o777) == "0o750"
