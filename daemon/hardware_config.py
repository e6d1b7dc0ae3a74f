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
are refused with :class:`HardwareConfigError` naming the file, the key and what is allowed.
"""

from __future__ import annotations

import hashlib
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from daemon.errors import DaemonError
from drivers.depth.base import DepthSource
from drivers.depth.kinds import DEPTH_KINDS
from planner.rig import MAX_STRING, Rig, RigConfigError, _int, _key_name, _num, _Reader, _str, show
from planner.yaml_files import read_yaml

MAX_FILE_BYTES = 256 * 1024
HARDWARE_FILE = "hardware.yaml"
CAN_INTERFACES = ("socketcan", "slcan", "socketcand", "virtual")
_HOST_PORT = re.compile(r"(?P<host>[A-Za-z0-9.-]{1,253}|\[[0-9A-Fa-f:]{2,39}\]):(?P<port>[0-9]{1,5})")


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


_TOP = {"can", "phones", "depth_cameras", "panel", "capture_agent", "timeouts"}
_CAN = {"interface": _str(), "channel": _str(), "host": _str(required=False, default=None),
        "port": _int(1, 65535, required=False, default=None),
        "bitrate": _int(10_000, 1_000_000, required=False, default=None)}
_PANEL = {"device": _str(), "baud": _int(1200, 4_000_000, required=False, default=115200)}
_TIMEOUTS = {"open_s": _num(0.5, 120.0, required=False, default=5.0),
             "phone_authorisation_s": _num(1.0, 600.0, required=False, default=60.0),
             "reprobe_s": _num(0.2, 60.0, required=False, default=2.0)}


def default_hardware_path(rig_path: Path | str) -> Path:
    """hardware.yaml beside the rig file."""
    return Path(rig_path).resolve().parent / HARDWARE_FILE


def load_hardware(path: Path | str, rig: Rig) -> HardwareConfig:
    """Read and validate a hardware file against the rig it wires."""
    path = Path(path)
    raw, text = read_yaml(path, max_bytes=MAX_FILE_BYTES, what="hardware file",
                          error=lambda problem: HardwareConfigError(path, "<file>", problem),
                          key_error=lambda key, problem: HardwareConfigError(path, key, problem))
    return hardware_from_mapping(raw, rig, path, hashlib.sha256(text).hexdigest())


def hardware_from_mapping(raw: Any, rig: Rig, path: Path | str = "<memory>", digest: str = "") -> HardwareConfig:
    reader = _HardwareReader(path)
    raw = reader.mapping(raw, "<top>")
    unknown = sorted(_key_name(k) for k in raw if k not in _TOP)
    if unknown:
        raise reader.error(unknown[0], f"unknown section; allowed: {', '.join(sorted(_TOP))}")
    for name in ("can", "phones", "depth_cameras", "panel"):
        if name not in raw:
            raise reader.error(name, "missing section" + (" (write 'panel: null' for a rig without one)"
                                                          if name == "panel" else ""))
    base = Path(path).parent
    agent = raw.get("capture_agent")
    if agent is not None:
        agent = base / reader.value(agent, "capture_agent", _str())
    return HardwareConfig(
        path=str(path), digest=digest, can=_can(reader, raw["can"]),
        phones=_phones(reader, raw["phones"], rig),
        depth_cameras=_depth(reader, raw["depth_cameras"], rig, base),
        panel=None if raw["panel"] is None else PanelPort(**reader.section(raw["panel"], "panel", _PANEL)),
        capture_agent=agent,
        timeouts=Timeouts(**reader.section(raw.get("timeouts") or {}, "timeouts", _TIMEOUTS)),
    )


class _HardwareReader(_Reader):
    def error(self, key: str, problem: str) -> HardwareConfigError:
        return HardwareConfigError(self.path, key, problem)


def _can(reader: _HardwareReader, raw: Any) -> CanBus:
    bus = CanBus(**reader.section(raw, "can", _CAN))
    if bus.interface not in CAN_INTERFACES:
        raise reader.error("can.interface", f"got {show(bus.interface)}; allowed: {', '.join(CAN_INTERFACES)}")
    needs_bridge = bus.interface == "socketcand"
    if needs_bridge and (bus.host is None or bus.port is None):
        raise reader.error("can.host" if bus.host is None else "can.port", "socketcand needs the bridge's host and port")
    if not needs_bridge and (bus.host is not None or bus.port is not None):
        raise reader.error("can.host" if bus.host is not None else "can.port",
                           f"only socketcand has a host and port, not {bus.interface}")
    if bus.bitrate is not None and bus.interface != "slcan":
        raise reader.error("can.bitrate", f"set by the OS for {bus.interface} (ip link); only slcan takes one")
    return bus


def _by_id(reader: _HardwareReader, raw: Any, key: str, ids: list[str]) -> dict[str, Any]:
    raw = reader.mapping(raw, key)
    unknown = sorted(_key_name(k) for k in raw if k not in ids)
    if unknown:
        raise reader.error(f"{key}.{unknown[0]}", f"not in the rig file; its ids are {', '.join(ids)}")
    for name in ids:
        if name not in raw:
            raise reader.error(f"{key}.{name}", "missing: every device of the rig file needs an address")
    return {name: raw[name] for name in ids}


def _one_key(reader: _HardwareReader, raw: Any, key: str, kinds: tuple[str, ...]) -> tuple[str, Any]:
    if isinstance(raw, str) and raw in kinds[:1]:
        return raw, None
    if not isinstance(raw, dict) or len(raw) != 1 or next(iter(raw)) not in kinds:
        raise reader.error(key, f"got {show(raw)}; expected '{kinds[0]}' or a mapping with one of "
                                f"{', '.join(kinds)}")
    kind, value = next(iter(raw.items()))
    return kind, value


def _phones(reader: _HardwareReader, raw: Any, rig: Rig) -> dict[str, PhoneLink]:
    serials = {p.id: p.serial for p in rig.phones}
    links = {}
    for name, entry in _by_id(reader, raw, "phones", list(serials)).items():
        key = f"phones.{name}"
        kind, value = _one_key(reader, entry, key, ("usb", "tcp"))
        if kind == "usb":
            if value is not None and _serial(reader, value, f"{key}.usb") != serials[name]:
                raise reader.error(f"{key}.usb", f"serial {show(value)} is not the rig file's {serials[name]!r} "
                                                 "for this phone (the rig file names each phone; write 'usb')")
            links[name] = PhoneLink(serials[name])
        else:
            host, port = _host_port(reader, value, f"{key}.tcp")
            links[name] = PhoneLink(serials[name], host, port)
    return links


def _depth(reader: _HardwareReader, raw: Any, rig: Rig, base: Path) -> dict[str, DepthSource]:
    """Each depth camera's kind (drivers/depth/kinds.py) and what it names: the rig file's serial,
    or a file (relative to the hardware file)."""
    serials = {c.id: c.serial for c in rig.depth_cameras}
    sources = {}
    for name, entry in _by_id(reader, raw, "depth_cameras", list(serials)).items():
        key = f"depth_cameras.{name}"
        if isinstance(entry, str) and entry in DEPTH_KINDS and DEPTH_KINDS[entry].takes == "serial":
            kind, value = entry, None
        else:
            kind, value = _one_key(reader, entry, key, tuple(DEPTH_KINDS))
        if DEPTH_KINDS[kind].takes == "serial":
            if value is not None and _serial(reader, value, f"{key}.{kind}") != serials[name]:
                raise reader.error(f"{key}.{kind}", f"serial {show(value)} is not the rig file's "
                                                    f"{serials[name]!r} (write '{kind}')")
            sources[name] = DepthSource(kind, serials[name])
        else:
            sources[name] = DepthSource(kind, serials[name], base / reader.value(value, f"{key}.{kind}", _str()))
    return sources


def _serial(reader: _HardwareReader, value: Any, key: str) -> str:
    """A serial as text, checked before it is converted: a string of at most MAX_STRING
    characters, or a number YAML read from digits (RealSense serials are digits)."""
    if isinstance(value, str) and len(value) <= MAX_STRING:
        return value
    if isinstance(value, int) and not isinstance(value, bool) and 0 <= value and value.bit_length() <= 64:
        return str(value)
    raise reader.error(key, f"got {show(value)}; expected the device's serial (text or digits)")


def _host_port(reader: _HardwareReader, value: Any, key: str) -> tuple[str, int]:
    match = _HOST_PORT.fullmatch(value) if isinstance(value, str) else None
    if match is None or not 0 < int(match["port"]) < 65536:
        raise reader.error(key, f"got {show(value)}; expected HOST:PORT, e.g. 192.168.50.11:5555")
    return match["host"].strip("[]"), int(match["port"])
