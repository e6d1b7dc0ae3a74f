"""The site file: how this rig reaches the clinic's DICOM services (``/etc/tbp-rig/site.yaml``).

The rig file says what the rig is, the hardware file how this PC reaches its devices; the site
file says where the clinic's worklist and archive are::

    ae_title: TBPRIG1                # this rig's AE title (the calling AE of every association)
    worklist:                        # optional: the Modality Worklist provider (C-FIND)
      host: ris.clinic.example
      port: 104
      called_aet: RISWL
      modality: XC                   # the scheduled steps asked for (XC: external-camera photography)
      station_aet: null              # optional: only steps scheduled on this station
    archive:                         # optional: every completed scan is exported by the daemon
      pacs: {host: pacs.clinic.example, port: 104, called_aet: PACS}   # C-STORE, or
      dicomweb: https://pacs.clinic.example/dicom-web                   # STOW-RS (one of the two)
      deidentify: false              # PS3.15 basic profile (research archives)
      retry: {first_s: 10, max_s: 600}  # back-off after an outage, doubling up to max_s
    tls:                             # optional: DICOM over TLS for pacs and worklist
      ca_file: /etc/tbp-rig/clinic-ca.pem
      cert_file: /etc/tbp-rig/rig.pem  # optional client certificate (mutual TLS)
      key_file: /etc/tbp-rig/rig.key

Relative paths are relative to the site file. Unknown keys and out-of-range values are refused
with :class:`SiteConfigError` naming the file and the key; the keys, forms and defaults are the
site file's table (planner/schema/tables.py), this module checks the relations between them.
"""

from __future__ import annotations

import ssl
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from daemon.errors import DaemonError
from planner.rig import RigConfigError
from planner.schema.nodes import Reader
from planner.schema.tables import AE, SITE_FILE

SITE_FILE_NAME = "site.yaml"


class SiteConfigError(DaemonError, RigConfigError):
    """The site file is unusable: names the file, the key and the problem."""


@dataclass(frozen=True)
class Peer:
    """A DICOM application entity reached over DIMSE: ``called_aet`` at ``host:port``."""

    host: str
    port: int
    called_aet: str

    def __str__(self) -> str:
        return f"{self.called_aet}@{self.host}:{self.port}"


@dataclass(frozen=True)
class Tls:
    """DICOM over TLS: the clinic's CA; optionally this rig's certificate and key."""

    ca_file: Path
    cert_file: Path | None = None
    key_file: Path | None = None

    def context(self) -> ssl.SSLContext:
        context = ssl.create_default_context(ssl.Purpose.SERVER_AUTH, cafile=str(self.ca_file))
        if self.cert_file is not None:
            context.load_cert_chain(str(self.cert_file), None if self.key_file is None else str(self.key_file))
        return context


@dataclass(frozen=True)
class WorklistSource:
    peer: Peer
    modality: str = "XC"
    station_aet: str | None = None


@dataclass(frozen=True)
class Archive:
    """Where completed scans go: a PACS over C-STORE or a DICOMweb service (STOW-RS)."""

    pacs: Peer | None
    dicomweb: str | None
    deidentify: bool = False
    retry_first_s: float = 10.0
    retry_max_s: float = 600.0

    def __str__(self) -> str:
        return str(self.pacs) if self.pacs is not None else str(self.dicomweb)


@dataclass(frozen=True)
class Site:
    path: str
    ae_title: str
    worklist: WorklistSource | None = None
    archive: Archive | None = None
    tls: Tls | None = None


def default_site_path(rig_path: Path | str) -> Path:
    """site.yaml beside the rig file."""
    return Path(rig_path).resolve().parent / SITE_FILE_NAME


def load_site(path: Path | str) -> Site:
    """Read and validate a site file."""
    values, _sha = SITE_FILE.load(path, SiteConfigError)
    return _site(values, path)


def site_from_mapping(raw: Any, path: Path | str = "<memory>") -> Site:
    """A site from an already-parsed document (validated like a file)."""
    return _site(SITE_FILE.check(raw, path, SiteConfigError), path)


def _site(values: dict[str, Any], path: Path | str) -> Site:
    base = Path(path).parent
    worklist = tls = archive = None
    if (w := values["worklist"]) is not None:
        station = w["station_aet"]
        worklist = WorklistSource(_peer(w), w["modality"], None if station is None else station.strip())
    if (t := values["tls"]) is not None:
        tls = Tls(base / t["ca_file"], *(None if t[k] is None else base / t[k] for k in ("cert_file", "key_file")))
    if (a := values["archive"]) is not None:
        if (a["pacs"] is None) == (a["dicomweb"] is None):
            raise SiteConfigError(str(path), "archive", "give exactly one of pacs (C-STORE) and dicomweb (STOW-RS)")
        retry = a["retry"]
        if retry["max_s"] < retry["first_s"]:
            raise SiteConfigError(str(path), "archive.retry.max_s",
                                  f"{retry['max_s']:g} is below first_s {retry['first_s']:g}")
        archive = Archive(None if a["pacs"] is None else _peer(a["pacs"]),
                          None if a["dicomweb"] is None else a["dicomweb"].rstrip("/"),
                          a["deidentify"], retry["first_s"], retry["max_s"])
    return Site(str(path), values["ae_title"].strip(), worklist, archive, tls)


def ae_title(value: Any, key: str, where: str = "command line") -> str:
    """An AE title given outside the site file (a command's option), checked as the site file's."""
    return str(AE.read(value, key, Reader(where, SiteConfigError))).strip()


def _peer(values: dict[str, Any]) -> Peer:
    return Peer(values["host"], values["port"], values["called_aet"].strip())
