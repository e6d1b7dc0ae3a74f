"""What the host writes into the beam drive at bring-up: heartbeats, PDO mapping, how it stops.

Kept as data plus one coroutine so the configuration can be read (and tested) in one place.
PDO mapping follows CiA 301's procedure: invalidate the PDO, clear the mapping count, write the
entries, set the count, set transmission type (and event timer), validate the PDO.

Every object that makes the drive stop by itself (:mod:`drivers.motor.stop_config`) is read
back after it is written: a drive that refuses one raises :class:`SettingRefused`, one that
reads back another value :class:`SettingMismatch`, both naming the object.
"""

from __future__ import annotations

from collections.abc import Awaitable, Callable

import can

from drivers.motor import cia402, nmt, pdo
from drivers.motor import stop_config as sc
from drivers.motor.errors import SdoAbort, SettingMismatch, SettingRefused
from drivers.motor.sdo import SdoClient
from planner.rig import Motor

# TPDO1: one BeamSample per frame. TPDO2: the statusword, for the state machine.
POSITION_TPDO = (
    pdo.MappedObject(cia402.POSITION_ACTUAL, 0, "<i"),
    pdo.MappedObject(cia402.VELOCITY_ACTUAL, 0, "<i"),
)
STATUS_TPDO = (pdo.MappedObject(cia402.STATUSWORD, 0, "<H"),)
CONTROL_RPDO = sc.CONTROL_RPDO

Write = Callable[[int, int, str, int, str], Awaitable[None]]
"""write(index, subindex, fmt, value, what): one object of the configuration."""


def event_timer_ms(motor: Motor) -> int:
    """The TPDO event timer for the rig's position rate, ms (at least 1)."""
    return max(1, round(1000 / motor.position_rate_hz))


def controlword_pdo(node_id: int, word: int) -> can.Message:
    """The RPDO1 frame writing ``word`` into the controlword of drive ``node_id`` (e.g.
    ``cia402.QUICK_STOP``): acted on at reception, no reply, no SDO transfer to wait for."""
    return can.Message(arbitration_id=nmt.rpdo_cob_id(sc.CONTROL_RPDO_NUMBER, node_id),
                       data=pdo.encode_pdo(CONTROL_RPDO, (word,)), is_extended_id=False)


async def write_checked(sdo: SdoClient, index: int, subindex: int, fmt: str, value: int, what: str) -> None:
    """Write one object and read it back.

    Raises:
        SettingRefused: the write or the read-back was answered with an SDO abort.
        SettingMismatch: the object reads back another value.
    """
    try:
        await sdo.write(index, subindex, fmt, value)
        read = await sdo.read(index, subindex, fmt)
    except SdoAbort as exc:
        raise SettingRefused(sdo.device, sdo.device_state(), index, subindex, what, value, exc.code) from exc
    if read != value:
        raise SettingMismatch(sdo.device, sdo.device_state(), index, subindex, what, value, read)


async def configure(sdo: SdoClient, motor: Motor, host_node_id: int) -> None:
    """Write the drive's stop configuration (read back), TPDO1/TPDO2 and the following error
    window; the heartbeat consumer last, once the drive knows how to react to its loss."""
    required = sc.required_stop_configuration(motor, host_node_id)

    async def checked(index: int, subindex: int, fmt: str, value: int, what: str) -> None:
        await write_checked(sdo, index, subindex, fmt, value, what)

    async def plain(index: int, subindex: int, fmt: str, value: int, what: str) -> None:
        await sdo.write(index, subindex, fmt, value)

    for setting in (sc.QUICK_STOP_DECELERATION, sc.QUICK_STOP_OPTION, sc.FAULT_REACTION, sc.ABORT_CONNECTION,
                    sc.COMMUNICATION_ERROR, sc.HEARTBEAT_PRODUCER):
        await checked(setting.index, setting.subindex, setting.fmt, getattr(required, setting.field),
                      setting.name)
    await map_pdo(checked, pdo.RPDO_COMMUNICATION, pdo.RPDO_MAPPING,
                  nmt.rpdo_cob_id(sc.CONTROL_RPDO_NUMBER, motor.node_id), CONTROL_RPDO, "RPDO1")
    for k, mapping in enumerate((POSITION_TPDO, STATUS_TPDO)):
        await map_pdo(plain, pdo.TPDO_COMMUNICATION + k, pdo.TPDO_MAPPING + k, nmt.tpdo_cob_id(k + 1, motor.node_id),
                      mapping, f"TPDO{k + 1}", event_timer_ms=event_timer_ms(motor))
    await sdo.write(cia402.FOLLOWING_ERROR_WINDOW, 0, "<I", round(motor.following_error_deg * motor.counts_per_degree))
    consumer = sc.HEARTBEAT_CONSUMER
    await checked(consumer.index, consumer.subindex, consumer.fmt, getattr(required, consumer.field), consumer.name)


async def map_pdo(write: Write, comm: int, mapping_index: int, cob_id: int, mapping: tuple[pdo.MappedObject, ...],
                  name: str, *, event_timer_ms: int | None = None) -> None:
    """CiA 301's PDO mapping procedure for one PDO, event driven (type 255)."""
    await write(comm, 1, "<I", pdo.COB_ID_INVALID | cob_id, f"{name} COB-ID (invalidate)")
    await write(mapping_index, 0, "<B", 0, f"{name} mapping count (clear)")
    for sub, obj in enumerate(mapping, start=1):
        await write(mapping_index, sub, "<I", obj.entry, f"{name} mapping entry {sub}")
    await write(mapping_index, 0, "<B", len(mapping), f"{name} mapping count")
    await write(comm, 2, "<B", pdo.TRANSMISSION_EVENT_DRIVEN, f"{name} transmission type")
    if event_timer_ms is not None:
        await write(comm, 5, "<H", event_timer_ms, f"{name} event timer")
    await write(comm, 1, "<I", cob_id, f"{name} COB-ID")
