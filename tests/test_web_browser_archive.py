"""A workstation without the rig PC: `tbp viewer --dicomweb URL` lists the archive's studies
(QIDO-RS), Open retrieves one (WADO-RS) and the viewer shows the body and, for a spot, the same
best image as on the rig (Chromium, Debian's Orthanc on loopback). Synthetic identities only."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import pytest

from analysis.navigate import navigate
from analysis.scan_views import open_scan
from tests.dicom_services import free_port, orthanc
from tests.test_web import folder_of
from tests.web_browser import canvas_is_blank, chromium, chromium_missing, wait_for

pytestmark = [pytest.mark.slow, pytest.mark.skipif(chromium_missing() is not None, reason=str(chromium_missing()))]
SHOTS = Path(os.environ.get("TBP_SCREENSHOTS", "/tmp/tbp-web-screenshots"))
TBP = str(Path(sys.executable).with_name("tbp"))


def test_a_study_is_opened_from_the_archive_by_dicomweb(web_store: Path, tmp_path: Path):
    scan = web_store / folder_of(web_store)
    point = open_scan(scan).mesh().vertices[4242].tolist()
    with orthanc(tmp_path / "orthanc") as server:
        sent = subprocess.run([TBP, "export", str(scan), "--dicomweb", server.dicomweb], capture_output=True, text=True)
        assert sent.returncode == 0, sent.stderr
        port = free_port()
        viewer = subprocess.Popen([TBP, "viewer", "--dicomweb", server.dicomweb, "--cache", str(tmp_path / "cache"),
                                   "--http", f"127.0.0.1:{port}"], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        url = f"http://127.0.0.1:{port}"
        try:
            deadline = time.monotonic() + 60
            while True:
                try:
                    urllib.request.urlopen(f"{url}/api/config", timeout=2).read()
                    break
                except OSError:
                    assert viewer.poll() is None and time.monotonic() < deadline, viewer.stderr.read().decode()[-2000:]
                    time.sleep(0.2)
            with chromium() as driver:
                driver.get(f"{url}/archive")
                wait_for(driver, "window.tbpArchive && window.tbpArchive.ready"
                                 " && document.querySelectorAll('#studies tbody tr').length === 1", 60)
                assert "Testperson, Capsule" in driver.find_element("id", "studies").text
                driver.find_element("css selector", "#studies button").click()
                assert wait_for(driver, "window.tbpViewer && (window.tbpViewer.ready || window.tbpViewer.error)", 300) is True
                assert driver.execute_script("return window.tbpViewer.error") is None
                assert "Testperson, Capsule (SYN-0001)" in driver.find_element("id", "title").text
                assert not canvas_is_blank(driver.find_element("css selector", "canvas").screenshot_as_png)
                SHOTS.mkdir(parents=True, exist_ok=True)
                driver.save_screenshot(str(SHOTS / "viewer-from-archive.png"))
                folder = driver.execute_script("return window.tbpViewer.folder")
            x, y, z = point
            answer = json.loads(urllib.request.urlopen(f"{url}/api/scans/{folder}/navigate?x={x}&y={y}&z={z}&count=3",
                                                       timeout=300).read())
        finally:
            viewer.terminate()
            viewer.wait(30)
    here = navigate(scan, point=",".join(map(str, point)), count=3)
    assert [v["file"] for v in answer["views"]] == [v["file"] for v in here["views"]]
