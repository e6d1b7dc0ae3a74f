"""The export queue through failures it was not written for, with the export replaced (no archive,
no scan): the scan's problem is shown, the transfer retried, the queue never stops."""

from __future__ import annotations

import asyncio
from pathlib import Path
from types import SimpleNamespace

import pytest

from archive.queue import PENDING, SENT, ExportQueue, ExportRecord
from archive.send import send_dimse
from daemon.clinic.dimse import TransferAborted
from daemon.clinic.site import Archive, Peer, Site
from daemon.records.store import ScanStore

PACS = Peer(host="127.0.0.1", port=11112, called_aet="ORTHANC")


async def test_an_unexpected_error_in_a_transfer_is_shown_and_retried_and_the_queue_goes_on(tmp_path: Path):
    site = Site(path="<test>", ae_title="TBPRIG1",
                archive=Archive(pacs=PACS, dicomweb=None, retry_first_s=0.01, retry_max_s=0.02))
    calls: list[str] = []

    def export(record: ExportRecord, on_sent) -> None:
        calls.append(record.folder)
        if len(calls) == 1:
            raise RuntimeError("a library's own failure")
        record.sent.append("1.2.3.4")

    queue = ExportQueue(ScanStore(tmp_path / "store"), site, export=export)
    await queue.start()
    try:
        queue.records["scan-1"] = ExportRecord("scan-1", str(site.archive))
        queue._wake.set()
        problem = None
        for _ in range(400):
            problem = problem or next(iter(queue.status()["problems"]), None)
            if queue.records["scan-1"].state == SENT:
                break
            await asyncio.sleep(0.01)
        assert queue._task is not None and not queue._task.done()
    finally:
        await queue.close()
    assert problem is not None and problem["state"] == PENDING, problem
    assert problem["error"] == "ORTHANC@127.0.0.1:11112: unexpected RuntimeError: a library's own failure"
    assert calls == ["scan-1", "scan-1"]
    assert queue.records["scan-1"].state == SENT and queue.records["scan-1"].error is None


class CutAssociation:
    """pynetdicom's association cut by the peer (its reactor thread) just as a C-STORE is asked for."""

    is_established = True

    def send_c_store(self, dataset):
        self.is_established = False
        raise RuntimeError("The association with a peer SCP must be established before sending a C-STORE request")


def test_a_cut_between_two_stores_is_a_transfer_aborted(monkeypatch: pytest.MonkeyPatch):
    instance = SimpleNamespace(sop_instance_uid="1.2.3.4", sop_class_uid="1.2.840.10008.5.1.4.1.1.77.1.4",
                               transfer_syntax="1.2.840.10008.1.2.4.50", kind="image", name="cam1_000.jpg")
    monkeypatch.setattr("archive.send.associate", lambda *args, **kwargs: CutAssociation())
    monkeypatch.setattr("archive.send.study_file", lambda instance: object())
    with pytest.raises(TransferAborted, match="ORTHANC@127.0.0.1:11112: association ended before image cam1_000.jpg"):
        send_dimse([instance], "TBPRIG1", PACS)
