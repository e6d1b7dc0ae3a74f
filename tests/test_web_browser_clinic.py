"""The console picks today's worklist patient and starts the scan for them: two clicks (Chromium
against `tbp daemon --sim` with a site file naming dcmtk's wlmscpfs). Synthetic identities only."""

from __future__ import annotations

import json
import os
from datetime import datetime
from pathlib import Path

import pytest

from tests.dicom_services import free_port, worklist_provider, write_worklist_item
from tests.sim_daemons import SimDaemon
from tests.test_archive_queue import wait_until
from tests.web_browser import chromium, chromium_missing, wait_for

pytestmark = [pytest.mark.slow, pytest.mark.skipif(chromium_missing() is not None, reason=str(chromium_missing()))]
SHOTS = Path(os.environ.get("TBP_SCREENSHOTS", "/tmp/tbp-web-screenshots"))


def test_a_worklist_patient_is_picked_and_scanned_in_two_clicks(tmp_path: Path):
    with worklist_provider(tmp_path / "wl") as (port, folder):
        today = f"{datetime.now().astimezone():%Y%m%d}"  # the worklist's local date
        write_worklist_item(folder, PatientName="Testperson^Clicka", PatientID="SYN-CLICK-1",
                            AccessionNumber="ACC-CLICK", ScheduledProcedureStepStartDate=today)
        write_worklist_item(folder, PatientName="Otherperson^Waits", PatientID="SYN-CLICK-2",
                            ScheduledProcedureStepStartDate=today)
        http = free_port()
        site = {"ae_title": "TBPRIG1", "worklist": {"host": "127.0.0.1", "port": port, "called_aet": "RISWL"}}
        daemon = SimDaemon(tmp_path / "rig", site=site, http=http)
        try:
            with chromium() as driver:
                driver.get(f"http://127.0.0.1:{http}/")
                wait_for(driver, "document.querySelectorAll('#worklist tr.pick').length === 2"
                                 " && window.tbpConsole.status && window.tbpConsole.status.state === 'IDLE'", 120)
                row = next(r for r in driver.find_elements("css selector", "#worklist tr.pick") if "SYN-CLICK-1" in r.text)
                row.click()  # click 1
                assert "Testperson, Clicka" in driver.find_element("id", "chosen").text
                driver.find_element("id", "start").click()  # click 2
                wait_for(driver, "window.tbpConsole.events.some(e => e.state === 'DEPTH_SWEEP')", 300)
                SHOTS.mkdir(parents=True, exist_ok=True)
                driver.save_screenshot(str(SHOTS / "console-worklist-scan.png"))
            assert daemon.tbp("abort").returncode == 0
            last = wait_until("the scan ended", lambda: daemon.status().get("last_scan"), timeout_s=300)
        finally:
            daemon.stop()
    manifest = json.loads((Path(last["folder"]) / "manifest.json").read_text())
    assert manifest["patient"]["patient_id"] == "SYN-CLICK-1" and manifest["patient"]["name"] == "Testperson^Clicka"
    assert manifest["study"]["accession_number"] == "ACC-CLICK"
