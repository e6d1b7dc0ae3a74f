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
with :class:`SiteConfigError` naming the file and the key.
"""

from __future__ import annotations

import re
import ssl
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from daemon.errors import DaemonError
from planner.rig import RigConfigError, _Field, _int, _key_name, _num, _Reader, _str, show
from planner.yaml_files import read_yaml

SITE_FILE = "site.yaml"
MAX_FILE_BYTES = 64 * 1024
AE_TITLE = re.compile(r"[ -\[\]-~]{1,16}")
"""An AE title: 1-16 characters of the default repertoire without backslash or control characters."""


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


_TOP = {"ae_title", "worklist", "archive", "tls"}
_PEER = {"host": _str(), "port": _int(1, 65535), "called_aet": _str()}
_WORKLIST = {**_PEER, "modality": _str(required=False, default="XC"),
             "station_aet": _str(required=False, default=None)}
_ARCHIVE = {"deidentify": _Field(bool, required=False, default=False)}
_RETRY = {"first_s": _num(0.1, 3600.0, required=False, default=10.0),
          "max_s": _num(1.0, 86400.0, required=False, default=600.0)}
_TLS = {"ca_file": _str(), "cert_file": _str(required=False, default=None),
        "key_file": _str(required=False, default=None)}


def default_site_path(rig_path: Path | str) -> Path:
    """site.yaml beside the rig file."""
    return Path(rig_path).resolve().parent / SITE_FILE


def load_site(path: Path | str) -> Site:
    """Read and validate a site file."""
    path = Path(path)
    raw, _text = read_yaml(path, max_bytes=MAX_FILE_BYTES, what="site file",
                           error=lambda problem: SiteConfigError(path, "<file>", problem),
                           key_error=lambda key, problem: SiteConfigError(path, key, problem))
    return site_from_mapping(raw, path)


class _SiteReader(_Reader):
    def error(self, key: str, problem: str) -> SiteConfigError:
        return SiteConfigError(self.path, key, problem)

    def ae(self, value: Any, key: str) -> str:
        if not isinstance(value, str) or not AE_TITLE.fullmatch(value) or not value.strip():
            raise self.error(key, f"got {show(value)}; expected an AE title: 1-16 printable ASCII characters, "
                                  "no backslash")
        return value.strip()

    def peer(self, raw: Any, key: str, table: dict[str, Any]) -> dict[str, Any]:
        values = self.section(raw, key, table)
        values["called_aet"] = self.ae(values["called_aet"], f"{key}.called_aet")
        return values


def site_from_mapping(raw: Any, path: Path | str = "<memory>") -> Site:
    reader = _SiteReader(path)
    raw = reader.mapping(raw, "<top>")
    unknown = sorted(_key_name(k) for k in raw if k not in _TOP)
    if unknown:
        raise reader.error(unknown[0], f"unknown section; allowed: {', '.join(sorted(_TOP))}")
    if "ae_title" not in raw:
        raise reader.error("ae_title", "missing; this rig's AE title, e.g. TBPRIG1")
    base = Path(path).parent
    worklist = None
    if raw.get("worklist") is not None:
        values = reader.peer(raw["worklist"], "worklist", _WORKLIST)
        station = values["station_aet"]
        worklist = WorklistSource(Peer(values["host"], values["port"], values["called_aet"]),
                                  values["modality"],
                                  None if station is None else reader.ae(station, "worklist.station_aet"))
    tls = None
    if raw.get("tls") is not None:
        values = reader.section(raw["tls"], "tls", _TLS)
        tls = Tls(*(None if values[k] is None else base / values[k] for k in ("ca_file", "cert_file", "key_file")))
    return Site(str(path), reader.ae(raw["ae_title"], "ae_title"), worklist,
                None if raw.get("archive") is None else _archive(reader, raw["archive"]), tls)


def _archive(reader: _SiteReader, raw: Any) -> Archive:
    raw = reader.mapping(raw, "archive")
    allowed = {"pacs", "dicomweb", "deidentify", "retry"}
    unknown = sorted(_key_name(k) for k in raw if k not in allowed)
    if unknown:
        raise reader.error(f"archive.{unknown[0]}", f"unknown key; allowed keys: {', '.join(sorted(allowed))}")
    if ("pacs" in raw) == ("dicomweb" in raw):
        raise reader.error("archive", "give exactly one of pacs (C-STORE) and dicomweb (STOW-RS)")
    pacs = None
    if "pacs" in raw:
        values = reader.peer(raw["pacs"], "archive.pacs", _PEER)
        pacs = Peer(values["host"], values["port"], values["called_aet"])
    url = None
    if "dicomweb" in raw:
        url = reader.value(raw["dicomweb"], "archive.dicomweb", _str())
        if not re.fullmatch(r"https?://[^\s]+", url):
            raise reader.error("archive.dicomweb", f"got {show(url)}; expected an http:// or https:// URL")
    deidentify = reader.section({k: raw[k] for k in ("deidentify",) if k in raw}, "archive", _ARCHIVE)["deidentify"]
    retry = reader.section(raw.get("retry") or {}, "archive.retry", _RETRY)
    if retry["max_s"] < retry["first_s"]:
        raise reader.error("archive.retry.max_s", f"{retry['max_s']:g} is below first_s {retry['first_s']:g}")
    return Archive(pacs, url.rstrip("/") if url else None, deidentify, retry["first_s"], retry["max_s"])
