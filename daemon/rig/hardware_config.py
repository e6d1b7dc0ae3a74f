"""The hardware file: how the daemon reaches every real device of the rig.

The rig file (``rig.yaml``) says what the rig is: geometry, optics, each phone's and depth
camera's identity (serial), the drive's node id and heartbeats. The hardware file
(``hardware.yaml``, beside the rig file; on a rig PC ``/etc/tbp-rig/hardware.yaml``) says how
this PC reaches them, and nothing else::

    can: {interface: socketcan, channel: can0}           # or slcan (channel /dev/ttyACM0, bitrate),
                                                         # or socketcand (host, port, channel)
    phones:                      # every phone of the rig file, by its id
      cam0: usb                  # over USB, found by the rig file's serial (ro.serialno)
      cam1: {tcp: "192.168.50.11:5555"}                  # ADB over TCP (wireless debugging)
    depth_cameras:               # every depth camera of the rig file, by its id
      depth0: realsense          # the RealSense with the rig file's serial
      depth1: {recording: recordings/depth1.db3}         # play a recorded sweep (.beam.json beside it)
    panel: {device: /dev/ttyACM1, baud: 115200}          # or null: a rig without a panel
    capture_agent: /opt/tbp-rig/agent/tbp-capture-agent.jar   # optional: pushed to phones without it
    timeouts: {open_s: 5.0, phone_authorisation_s: 60.0, reprobe_s: 2.0}   # optional

The depth cameras' kinds are drivers/depth/kinds.py's. ``{usb: SERIAL}`` and ``{realsense: SERIAL}``
are accepted when SERIAL is the rig file's. Relative
paths are relative to the hardware file. Unknown keys, missing devices and out-of-range values
are refused with :class:`HardwareConfigError` naming the file, the key and what is allowed. The
keys, forms and defaults are the hardware file's table (planner/schema/tables.py), its depth
cameras reached in one of :func:`depth_kinds`; this module checks the file against the rig file.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from daemon.errors import DaemonError
from drivers.depth.base import DepthSource
from drivers.depth.kinds import DEPTH_KINDS as DEPTH_DRIVERS
from planner.rig import Rig, RigConfigError
from planner.schema import ConfigFile, Kind, Nullable, Serial, Text, key_name, show
from planner.schema.tables import HOST_PORT, PHONE_LINKS, hardware_file

HARDWARE_FILE = "hardware.yaml"


def depth_kinds() -> dict[str, Kind]:
    """How a depth camera may be reached: the registry's kinds (drivers/depth/kinds.py, read at each
    call, so a kind registered later is accepted) -> the form of their value in the hardware file:
    a kind that names a serial is written bare or with the rig file's serial, one that names a file
    with its path."""
    return {name: Kind(Nullable(Serial()), bare=True, doc=kind.doc) if kind.takes == "serial"
            else Kind(Text(), doc=kind.doc) for name, kind in DEPTH_DRIVERS.items()}


def hardware_table() -> ConfigFile:
    """The hardware file's table with the depth camera kinds registered now."""
    return hardware_file(depth_kinds())


HARDWARE = hardware_table()
"""The hardware file's table with the registry's built-in kinds (docs/configuration.md)."""
MAX_FILE_BYTES = HARDWARE.max_bytes


class HardwareConfigError(DaemonError, RigConfigError):
    """The hardware file is unusable: names the file, the key and the problem."""


@dataclass(frozen=True)
class CanBus:
    """python-can's ``interface`` and ``channel``; socketcand adds its bridge's host and port,
    slcan (a serial adapter) the bus bitrate (kernel buses have it set by the OS)."""

    interface: str
    channel: str
    host: str | None = None
    port: int | None = None
    bitrate: int | None = None

    @property
    def address(self) -> str:
        if self.interface == "socketcand":
            return f"socketcand://{self.host}:{self.port}/{self.channel}"
        return f"{self.interface}:{self.channel}"

    def bus_options(self) -> dict[str, Any]:
        """Extra keyword arguments for ``can.Bus`` beyond interface and channel."""
        if self.interface == "socketcand":
            return {"host": self.host, "port": self.port}
        if self.interface == "slcan" and self.bitrate is not None:
            return {"bitrate": self.bitrate}
        return {}


@dataclass(frozen=True)
class PhoneLink:
    """How one phone is reached: over USB by its serial, or ADB over TCP at host:port."""

    serial: str
    host: str | None = None
    port: int | None = None

    @property
    def usb(self) -> bool:
        return self.host is None

    @property
    def address(self) -> str:
        return f"usb:{self.serial}" if self.usb else f"tcp:{self.host}:{self.port}"


@dataclass(frozen=True)
class PanelPort:
    device: str
    baud: int

    @property
    def address(self) -> str:
        return f"{self.device}@{self.baud}"


@dataclass(frozen=True)
class Timeouts:
    """open_s: each device's open (connect, handshake); phone_authorisation_s: a phone's first
    connection, while someone accepts the USB debugging prompt on it; reprobe_s: how often a
    missing device is tried again."""

    open_s: float = 5.0
    phone_authorisation_s: float = 60.0
    reprobe_s: float = 2.0


@dataclass(frozen=True)
class HardwareConfig:
    path: str
    digest: str
    can: CanBus
    phones: dict[str, PhoneLink]
    depth_cameras: dict[str, DepthSource]
    panel: PanelPort | None
    capture_agent: Path | None = None
    timeouts: Timeouts = field(default_factory=Timeouts)

    def devices(self) -> list[tuple[str, str]]:
        """(device, address) of every configured device, in bring-up order."""
        out = [("drive", self.can.address)]
        out += [(name, link.address) for name, link in self.phones.items()]
        out += [(name, src.address) for name, src in self.depth_cameras.items()]
        if self.panel is not None:
            out.append(("panel", self.panel.address))
        return out


def default_hardware_path(rig_path: Path | str) -> Path:
    """hardware.yaml beside the rig file."""
    return Path(rig_path).resolve().parent / HARDWARE_FILE


def load_hardware(path: Path | str, rig: Rig) -> HardwareConfig:
    """Read and validate a hardware file against the rig it wires."""
    values, digest = hardware_table().load(path, HardwareConfigError)
    return _hardware(values, rig, str(path), digest)


def hardware_from_mapping(raw: Any, rig: Rig, path: Path | str = "<memory>", digest: str = "") -> HardwareConfig:
    """Validate an already-parsed hardware mapping (see :func:`load_hardware`)."""
    return _hardware(hardware_table().check(raw, path, HardwareConfigError), rig, str(path), digest)


def _hardware(v: dict[str, Any], rig: Rig, path: str, digest: str) -> HardwareConfig:
    base = Path(path).parent
    return HardwareConfig(
        path=path, digest=digest, can=_can(path, v["can"]),
        phones=_phones(path, v["phones"], rig),
        depth_cameras=_depth(path, v["depth_cameras"], rig, base),
        panel=None if v["panel"] is None else PanelPort(**v["panel"]),
        capture_agent=None if v["capture_agent"] is None else base / v["capture_agent"],
        timeouts=Timeouts(**v["timeouts"]),
    )


def _can(path: str, values: dict[str, Any]) -> CanBus:
    bus = CanBus(**values)
    needs_bridge = bus.interface == "socketcand"
    if needs_bridge and (bus.host is None or bus.port is None):
        raise HardwareConfigError(path, "can.host" if bus.host is None else "can.port",
                                  "socketcand needs the bridge's host and port")
    if not needs_bridge and (bus.host is not None or bus.port is not None):
        raise HardwareConfigError(path, "can.host" if bus.host is not None else "can.port",
                                  f"only socketcand has a host and port, not {bus.interface}")
    if bus.bitrate is not None and bus.interface != "slcan":
        raise HardwareConfigError(path, "can.bitrate",
                                  f"set by the OS for {bus.interface} (ip link); only slcan takes one")
    return bus


def _by_id(path: str, entries: dict[str, Any], key: str, ids: list[str]) -> dict[str, Any]:
    """The entries of the rig file's devices, in its order; every one there, no other."""
    unknown = sorted(key_name(k) for k in entries if k not in ids)
    if unknown:
        raise HardwareConfigError(path, f"{key}.{unknown[0]}", f"not in the rig file; its ids are {', '.join(ids)}")
    for name in ids:
        if name not in entries:
            raise HardwareConfigError(path, f"{key}.{name}", "missing: every device of the rig file needs an address")
    return {name: entries[name] for name in ids}


def _phones(path: str, entries: dict[str, Any], rig: Rig) -> dict[str, PhoneLink]:
    serials = {p.id: p.serial for p in rig.phones}
    links = {}
    for name, (kind, value) in _by_id(path, entries, "phones", list(serials)).items():
        key = f"phones.{name}.{kind}"
        if kind == "usb":
            if value is not None and value != serials[name]:
                raise HardwareConfigError(path, key, f"serial {key_name(value)} is not the rig file's {serials[name]!r} "
                                                     "for this phone (the rig file names each phone; write 'usb')")
            links[name] = PhoneLink(serials[name])
        else:
            match = HOST_PORT.fullmatch(value)
            if match is None or not 0 < int(match["port"]) < 65536:
                raise HardwareConfigError(path, key, f"got {show(value)}; expected {PHONE_LINKS['tcp'].value.form()}")
            links[name] = PhoneLink(serials[name], match["host"].strip("[]"), int(match["port"]))
    return links


def _depth(path: str, entries: dict[str, Any], rig: Rig, base: Path) -> dict[str, DepthSource]:
    """Each depth camera's kind (drivers/depth/kinds.py) and what it names: the rig file's serial,
    or a file (relative to the hardware file)."""
    serials = {c.id: c.serial for c in rig.depth_cameras}
    sources = {}
    for name, (kind, value) in _by_id(path, entries, "depth_cameras", list(serials)).items():
        if DEPTH_DRIVERS[kind].takes == "serial":
            if value is not None and value != serials[name]:
                raise HardwareConfigError(path, f"depth_cameras.{name}.{kind}", f"serial {key_name(value)} is not "
                                                                                f"the rig file's {serials[name]!r} "
                                                                                f"(write '{kind}')")
            sources[name] = DepthSource(kind, serials[name])
        else:
            sources[name] = DepthSource(kind, serials[name], base / value)
    return sources
