"""Real DICOM services for the tests, started here on loopback with free ports and temporary
folders: Debian's Orthanc with its DICOMweb plugin (the archive), dcmtk's wlmscpfs (the worklist
provider). Each test that uses them is marked ``slow``; they skip, saying why, where the Debian
packages are not installed (./dev installs them)."""

from __future__ import annotations

import contextlib
import json
import shutil
import signal
import socket
import subprocess
import time
import urllib.request
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

DICOMWEB_PLUGIN = Path("/usr/share/orthanc/plugins/libOrthancDicomWeb.so")
ORTHANC_AET = "ORTHANC"
START_TIMEOUT_S = 60.0


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def need(program: str) -> str:
    found = shutil.which(program) or (f"/usr/sbin/{program}" if Path(f"/usr/sbin/{program}").exists() else None)
    if found is None:
        pytest.skip(f"{program} is not installed (./dev installs orthanc, orthanc-dicomweb, dcmtk, dicom3tools)")
    return found


def _wait_for_port(port: int, process: subprocess.Popen[bytes], log: Path) -> None:
    """Until something accepts on 127.0.0.1:port (the process's own deadline: START_TIMEOUT_S)."""
    deadline = time.monotonic() + START_TIMEOUT_S
    while time.monotonic() < deadline:
        if process.poll() is not None:
            raise RuntimeError(f"exited with {process.returncode}: {log.read_text()[-2000:]}")
        with contextlib.suppress(OSError), socket.create_connection(("127.0.0.1", port), timeout=0.5):
            return
        time.sleep(0.1)
    raise RuntimeError(f"not listening on {port} after {START_TIMEOUT_S:g} s: {log.read_text()[-2000:]}")


def _wait_for_echo(port: int, aet: str, process: subprocess.Popen[bytes], log: Path) -> None:
    """Until the process itself answers a C-ECHO as ``aet`` on 127.0.0.1:port: a port that merely
    accepts may be another process's that took the free port first (then this one has exited)."""
    from pynetdicom import AE
    from pynetdicom.sop_class import Verification

    deadline = time.monotonic() + START_TIMEOUT_S
    while time.monotonic() < deadline:
        if process.poll() is not None:
            raise RuntimeError(f"exited with {process.returncode}: {log.read_text()[-2000:]}")
        ae = AE(ae_title="TBPTEST")
        ae.add_requested_context(Verification)
        ae.acse_timeout = ae.network_timeout = ae.connection_timeout = 2.0
        assoc = ae.associate("127.0.0.1", port, ae_title=aet)
        if assoc.is_established:
            status = assoc.send_c_echo()
            assoc.release()
            if status and status.Status == 0:
                return
        time.sleep(0.1)
    raise RuntimeError(f"no C-ECHO answer as {aet} on {port} after {START_TIMEOUT_S:g} s: {log.read_text()[-2000:]}")


class Orthanc:
    """One Orthanc on loopback: ``dicom_port`` (AE ``ORTHANC``), ``http_port`` (REST and DICOMweb
    at ``/dicom-web``); its database survives :meth:`kill` and :meth:`start` (a restart)."""

    def __init__(self, root: Path, *, aet: str = ORTHANC_AET) -> None:
        self.binary = need("Orthanc")
        if not DICOMWEB_PLUGIN.exists():
            pytest.skip("orthanc-dicomweb is not installed")
        self.root = root
        self.aet = aet
        self.dicom_port = free_port()
        self.http_port = free_port()
        self.process: subprocess.Popen[bytes] | None = None
        root.mkdir(parents=True, exist_ok=True)
        self.config = root / "orthanc.json"
        self.config.write_text(json.dumps({
            "Name": "tbp-test", "StorageDirectory": str(root / "storage"), "IndexDirectory": str(root / "index"),
            "HttpPort": self.http_port, "DicomPort": self.dicom_port, "DicomAet": aet,
            "RemoteAccessAllowed": False, "AuthenticationEnabled": False, "DicomCheckCalledAet": True,
            "DicomAlwaysAllowStore": True, "DicomAlwaysAllowEcho": True, "HttpBindAddress": "127.0.0.1",
            "Plugins": [str(DICOMWEB_PLUGIN)],
            "DicomWeb": {"Enable": True, "Root": "/dicom-web/", "EnableWado": True},
            "StableAge": 1, "ConcurrentJobs": 1, "HttpThreadsCount": 8,
        }, indent=1))

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.http_port}"

    @property
    def dicomweb(self) -> str:
        return f"{self.url}/dicom-web"

    def start(self) -> Orthanc:
        log = self.root / "orthanc.log"
        self.process = subprocess.Popen([self.binary, str(self.config)], stdout=open(log, "ab"),
                                        stderr=subprocess.STDOUT)
        _wait_for_port(self.http_port, self.process, log)
        _wait_for_port(self.dicom_port, self.process, log)
        return self

    def kill(self) -> None:
        """SIGKILL: the archive gone at once, as in a power cut."""
        if self.process is not None and self.process.poll() is None:
            self.process.send_signal(signal.SIGKILL)
            self.process.wait(timeout=30)

    def stop(self) -> None:
        if self.process is not None and self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.wait(timeout=30)
            except subprocess.TimeoutExpired:
                self.kill()

    def get(self, path: str) -> Any:
        with urllib.request.urlopen(self.url + path, timeout=30) as answer:
            return json.loads(answer.read())

    def studies(self) -> list[dict[str, Any]]:
        return [self.get(f"/studies/{s}") for s in self.get("/studies")]

    def instances_of(self, study_uid: str) -> list[dict[str, Any]]:
        """The instances of a study with their main tags (SOPInstanceUID, SOPClassUID, series)."""
        for study in self.studies():
            if study["MainDicomTags"].get("StudyInstanceUID") == study_uid:
                return [self.get(f"/instances/{i['ID']}") for i in self.get(f"/studies/{study['ID']}/instances")]
        return []


@contextlib.contextmanager
def orthanc(root: Path) -> Iterator[Orthanc]:
    server = Orthanc(root).start()
    try:
        yield server
    finally:
        server.stop()


def write_worklist_item(folder: Path, **fields: Any) -> Path:
    """One scheduled step as a .wl file wlmscpfs serves (keywords as pydicom's)."""
    from pydicom.dataset import Dataset, FileMetaDataset
    from pydicom.uid import ExplicitVRLittleEndian, generate_uid

    step = Dataset()
    step.Modality = fields.pop("Modality", "XC")
    step.ScheduledStationAETitle = fields.pop("ScheduledStationAETitle", "TBPRIG1")
    step.ScheduledProcedureStepStartDate = fields.pop("ScheduledProcedureStepStartDate", "20300101")
    step.ScheduledProcedureStepStartTime = fields.pop("ScheduledProcedureStepStartTime", "0900")
    step.ScheduledProcedureStepDescription = "Total body photography"
    step.ScheduledProcedureStepID = "SPS1"
    step.ScheduledPerformingPhysicianName = ""
    step.ScheduledStationName = "TBP"
    step.ScheduledProcedureStepLocation = ""
    ds = Dataset()
    ds.SpecificCharacterSet = fields.pop("SpecificCharacterSet", "ISO_IR 192")
    ds.AccessionNumber = ""
    ds.RequestedProcedureDescription = "Total body photography"
    ds.RequestedProcedureID = "RP1"
    ds.RequestedProcedurePriority = ""
    ds.ReferringPhysicianName = ""
    ds.RequestingPhysician = ""
    ds.StudyInstanceUID = generate_uid()
    ds.PatientBirthDate = ""
    ds.PatientSex = ""
    for keyword, value in fields.items():
        setattr(ds, keyword, value)
    ds.ScheduledProcedureStepSequence = [step]
    ds.file_meta = FileMetaDataset()
    ds.file_meta.TransferSyntaxUID = ExplicitVRLittleEndian
    ds.file_meta.MediaStorageSOPClassUID = "1.2.276.0.7230010.3.1.0.1"
    ds.file_meta.MediaStorageSOPInstanceUID = generate_uid()
    path = folder / f"{ds.file_meta.MediaStorageSOPInstanceUID}.wl"
    ds.save_as(path, enforce_file_format=True)
    return path


@contextlib.contextmanager
def worklist_provider(root: Path, aet: str = "RISWL", *, keep_charset: bool = True) -> Iterator[tuple[int, Path]]:
    """dcmtk's wlmscpfs serving the .wl files in ``root/aet``: (port, that folder).
    ``keep_charset``: answers carry the files' Specific Character Set (else none, wlmscpfs's
    default: a provider that sends UTF-8 names without saying so)."""
    binary = need("wlmscpfs")
    folder = root / aet
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "lockfile").touch()
    port = free_port()
    log = root / "wlmscpfs.log"
    charset = ["-csk"] if keep_charset else []
    process = subprocess.Popen([binary, *charset, "-dfp", str(root), str(port)], stdout=open(log, "ab"),
                               stderr=subprocess.STDOUT)
    try:
        _wait_for_echo(port, aet, process, log)
        yield port, folder
    finally:
        process.terminate()
        process.wait(timeout=30)
