"""The daemon exports every completed scan by itself (`tbp daemon --sim` with a site file, Orthanc on
loopback): the archive killed mid-export and the daemon restarted while it is down, then the
archive back: the study complete, every instance exactly once. Synthetic identities only."""

from __future__ import annotations

import time
from collections import Counter
from pathlib import Path

import pytest

from daemon.records.store import read_folder
from tests.daemon_rigs import sparse_rig_file
from tests.dicom_services import Orthanc
from tests.sim_daemons import SimDaemon

pytestmark = pytest.mark.slow


def wait_until(what: str, check, timeout_s: float = 300.0, every_s: float = 0.5):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        value = check()
        if value:
            return value
        time.sleep(every_s)
    raise AssertionError(f"not within {timeout_s:g} s: {what}")


def test_orthanc_killed_mid_export_and_the_daemon_restarted_the_study_arrives_once(tmp_path: Path):
    server = Orthanc(tmp_path / "orthanc").start()
    site = {"ae_title": "TBPRIG1", "archive": {"pacs": {"host": "127.0.0.1", "port": server.dicom_port,
                                                        "called_aet": "ORTHANC"},
                                               "retry": {"first_s": 1, "max_s": 4}}}
    # four pictures per speed sector (112 in all): enough for the archive to go down mid-export
    rig = sparse_rig_file(tmp_path / "config", captures_per_sector=4)
    daemon = SimDaemon(tmp_path / "rig", site=site, rig=rig)
    try:
        folder = daemon.scan("--patient-id", "SYN-QUEUE-1", "--patient-name", "Testperson^Queue")
        study = read_folder(folder).manifest.study.study_instance_uid
        sending = wait_until("the export is under way",
                             lambda: (daemon.status().get("archive") or {}).get("sending") or None)
        wait_until("some instances confirmed", lambda: (daemon.status()["archive"]["sending"] or {}).get("sent", 0) >= 40)
        server.kill()
        problem = wait_until("the outage shown", lambda: daemon.status()["archive"]["problems"])
        assert "ORTHANC@127.0.0.1" in problem[0]["error"], problem
        assert daemon.stop() == 0
        daemon = SimDaemon(tmp_path / "rig", site=site, rig=rig)  # the same store: the queue is on disk
        # The study is queued again from disk: waiting, or already being tried against the archive
        # that is still down (which of the two depends on when this status is read).
        counts = daemon.status()["archive"]["counts"]
        assert counts["pending"] + counts["sending"] == 1 and counts["sent"] == counts["failed"] == 0, counts
        server.start()
        wait_until("the study sent", lambda: daemon.status()["archive"]["counts"]["sent"] == 1)
        record = daemon.status()["archive"]
        assert record["counts"] == {"pending": 0, "sending": 0, "sent": 1, "failed": 0}, record
    finally:
        daemon.stop()
        instances = server.instances_of(study) if server.process and server.process.poll() is None else []
        server.stop()
    uids = Counter(i["MainDicomTags"]["SOPInstanceUID"] for i in instances)
    verified = sum(i.status.value == "verified" for i in read_folder(folder).manifest.images)
    assert len(uids) == verified + 2 and set(uids.values()) == {1}  # images, mesh, QA report; no marks
    assert sending["folder"] == folder.name
