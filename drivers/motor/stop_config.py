"""What makes the beam drive stop by itself when the host dies, as data.

The rig requires of its drive: a heartbeat consumer watching the host (0x1016:1), an abort
connection option (0x6007) that turns a lost heartbeat into a fault, a fault reaction (0x605E)
on the quick-stop ramp (0x6085), the quick stop option (0x605A), an error behaviour (0x1029:1)
that keeps the drive OPERATIONAL so its TPDOs and EMCY keep reporting, and RPDO1 mapped to the
controlword so a quick stop is one frame. :func:`required_stop_configuration` gives these values
for a rig, :func:`read_stop_configuration` what a drive holds, and
:meth:`StopConfiguration.deviations` the differences, each naming the object.
"""

from __future__ import annotations

import enum
from collections.abc import Callable
from dataclasses import dataclass

from drivers.motor import cia402, nmt, pdo
from drivers.motor.errors import SdoAbort
from drivers.motor.sdo import SdoClient
from planner.rig import Motor

# RPDO1: the controlword, so one frame commands the drive (a quick stop needs no SDO round trip).
CONTROL_RPDO = (pdo.MappedObject(cia402.CONTROLWORD, 0, "<H"),)
CONTROL_RPDO_NUMBER = 1


def _enum_text(kind: type[enum.IntEnum]) -> Callable[[int], str]:
    def show(value: int) -> str:
        try:
            return f"{value} ({kind(value).name.lower().replace('_', ' ')})"
        except ValueError:
            return f"{value} (not a standard value)"

    return show


def _consumer_text(value: int) -> str:
    node, time_ms = nmt.parse_consumer_heartbeat(value)
    return f"node {node}, {time_ms} ms" if time_ms else "off"


def _cob_id_text(value: int) -> str:
    return f"0x{value & 0x7FF:03X}" + (" (invalid)" if value & pdo.COB_ID_INVALID else "")


def _mapping_text(entries: tuple[int, ...]) -> str:
    if not entries:
        return "nothing mapped"
    return ", ".join("0x{:04X}:{} {} bit".format(*pdo.parse_map_entry(e)) for e in entries)


@dataclass(frozen=True)
class Setting:
    """One object of the stop configuration: where it is, its struct format, its name, and how a
    value of it reads to a person."""

    field: str
    index: int
    subindex: int
    fmt: str
    name: str
    show: Callable[[int], str] = str

    @property
    def address(self) -> str:
        return f"0x{self.index:04X}:{self.subindex}"


QUICK_STOP_DECELERATION = Setting(
    "quick_stop_deceleration", cia402.QUICK_STOP_DECELERATION, 0, "<I", "quick-stop deceleration",
    lambda v: f"{v} counts/s^2")
QUICK_STOP_OPTION = Setting("quick_stop_option", cia402.QUICK_STOP_OPTION, 0, "<h", "quick stop option code",
                            _enum_text(cia402.QuickStopOption))
FAULT_REACTION = Setting("fault_reaction", cia402.FAULT_REACTION_OPTION, 0, "<h", "fault reaction option code",
                         _enum_text(cia402.FaultReaction))
ABORT_CONNECTION = Setting("abort_connection", cia402.ABORT_CONNECTION_OPTION, 0, "<h",
                           "abort connection option code", _enum_text(cia402.AbortConnection))
COMMUNICATION_ERROR = Setting("communication_error", cia402.ERROR_BEHAVIOUR, 1, "<B",
                              "error behaviour on a communication error",
                              _enum_text(nmt.CommunicationErrorBehaviour))
HEARTBEAT_PRODUCER = Setting("heartbeat_producer_ms", cia402.HEARTBEAT_PRODUCER, 0, "<H",
                             "heartbeat producer time", lambda v: f"{v} ms" if v else "off")
HEARTBEAT_CONSUMER = Setting("heartbeat_consumer", cia402.HEARTBEAT_CONSUMER, 1, "<I",
                             "heartbeat consumer of the host", _consumer_text)
CONTROL_RPDO_COB_ID = Setting("control_rpdo_cob_id", pdo.RPDO_COMMUNICATION, 1, "<I", "RPDO1 COB-ID",
                              _cob_id_text)
CONTROL_RPDO_TRANSMISSION = Setting("control_rpdo_transmission", pdo.RPDO_COMMUNICATION, 2, "<B",
                                    "RPDO1 transmission type",
                                    lambda v: f"{v} (event driven)" if v >= 0xFE else f"{v} (synchronous)")
CONTROL_RPDO_MAPPING = Setting("control_rpdo_mapping", pdo.RPDO_MAPPING, 0, "<B", "RPDO1 mapping")

SETTINGS = (
    QUICK_STOP_DECELERATION, QUICK_STOP_OPTION, FAULT_REACTION, ABORT_CONNECTION, COMMUNICATION_ERROR,
    HEARTBEAT_PRODUCER, HEARTBEAT_CONSUMER, CONTROL_RPDO_COB_ID, CONTROL_RPDO_TRANSMISSION,
    CONTROL_RPDO_MAPPING,
)
"""Every object of the stop configuration, in the order of :class:`StopConfiguration`'s fields."""


@dataclass(frozen=True)
class SettingRow:
    """One object as the drive holds it beside what the rig requires."""

    address: str
    name: str
    value: int | tuple[int, ...] | None
    required: int | tuple[int, ...]
    shown: str
    required_shown: str

    @property
    def ok(self) -> bool:
        return self.value == self.required

    def __str__(self) -> str:
        if self.ok:
            return f"{self.address} {self.name} = {self.shown}"
        return f"{self.address} {self.name} is {self.shown}, the rig requires {self.required_shown}"


@dataclass(frozen=True)
class StopConfiguration:
    """The objects that make the drive stop by itself, as read from it (None: the drive answered
    the read with an SDO abort, it lacks the object). Units: deceleration counts/s^2, times ms;
    ``heartbeat_consumer`` is the raw 0x1016:1 entry (node << 16 | ms), ``control_rpdo_mapping``
    the mapping entries of RPDO1 (index << 16 | sub-index << 8 | bits)."""

    quick_stop_deceleration: int | None
    quick_stop_option: int | None
    fault_reaction: int | None
    abort_connection: int | None
    communication_error: int | None
    heartbeat_producer_ms: int | None
    heartbeat_consumer: int | None
    control_rpdo_cob_id: int | None
    control_rpdo_transmission: int | None
    control_rpdo_mapping: tuple[int, ...] | None

    def rows(self, motor: Motor, host_node_id: int) -> list[SettingRow]:
        """Every object beside the value the rig requires of it."""
        required = required_stop_configuration(motor, host_node_id)
        return [_row(setting, getattr(self, setting.field), getattr(required, setting.field))
                for setting in SETTINGS]

    def deviations(self, motor: Motor, host_node_id: int) -> list[SettingRow]:
        """The objects whose value differs from what the rig requires (empty: the drive stops
        by itself as docs/motor.md describes)."""
        return [row for row in self.rows(motor, host_node_id) if not row.ok]


def _row(setting: Setting, value: int | tuple[int, ...] | None, required: int | tuple[int, ...]) -> SettingRow:
    def show(v: int | tuple[int, ...] | None) -> str:
        if v is None:
            return "missing (the drive refuses to read it)"
        return _mapping_text(v) if isinstance(v, tuple) else setting.show(v)

    return SettingRow(setting.address, setting.name, value, required, show(value), show(required))


def required_stop_configuration(motor: Motor, host_node_id: int) -> StopConfiguration:
    """The values the rig writes (bring-up) and requires (``tbp check``)."""
    return StopConfiguration(
        quick_stop_deceleration=round(motor.max_acceleration_deg_s2 * motor.counts_per_degree),
        quick_stop_option=cia402.QuickStopOption.QUICK_STOP_RAMP_STAY,
        fault_reaction=cia402.FaultReaction.QUICK_STOP_RAMP,
        abort_connection=cia402.AbortConnection.FAULT,
        communication_error=nmt.CommunicationErrorBehaviour.NO_CHANGE,
        heartbeat_producer_ms=motor.heartbeat_producer_ms,
        heartbeat_consumer=nmt.consumer_heartbeat_value(host_node_id, motor.heartbeat_timeout_ms),
        control_rpdo_cob_id=nmt.rpdo_cob_id(CONTROL_RPDO_NUMBER, motor.node_id),
        control_rpdo_transmission=pdo.TRANSMISSION_EVENT_DRIVEN,
        control_rpdo_mapping=tuple(m.entry for m in CONTROL_RPDO),
    )


async def read_stop_configuration(sdo: SdoClient) -> StopConfiguration:
    """What the drive holds of the stop configuration (SDO uploads; an object the drive refuses
    to read reads None)."""

    async def read(index: int, subindex: int, fmt: str) -> int | None:
        try:
            return await sdo.read(index, subindex, fmt)
        except SdoAbort:
            return None

    values: dict[str, int | tuple[int, ...] | None] = {}
    for setting in SETTINGS:
        values[setting.field] = await read(setting.index, setting.subindex, setting.fmt)
    count = values[CONTROL_RPDO_MAPPING.field]
    if isinstance(count, int):
        entries = [await read(pdo.RPDO_MAPPING, sub, "<I") for sub in range(1, min(count, 8) + 1)]
        values[CONTROL_RPDO_MAPPING.field] = (
            None if any(e is None for e in entries) else tuple(e for e in entries if e is not None))
    return StopConfiguration(**values)  # type: ignore[arg-type]

